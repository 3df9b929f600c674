// Host emulation of the CUDA kernel language subset used by ams_torch's .cu files, so that every
// kernel runs in `make test` on a machine without a GPU (ams_torch/native/emulation.py compiles
// each .cu file as host C++ with this header force-included, after rewriting the launch syntax
// `k<<<grid, block, shmem, stream>>>(args)` into `k | ams_emu::LaunchConfig(...)(args)`).
//
// Execution model (a correct CUDA schedule, not a performance model):
//   * a launch checks the configuration like the driver (block ≤ 1024 threads and ≤ 1024 × 1024
//     × 64, grid ≤ 2³¹−1 × 65535 × 65535, non-zero, dynamic shared memory ≤ 48 KiB unless the
//     kernel opted in) and sets cudaGetLastError() instead of running when it is wrong;
//   * blocks run one after another (or on AMS_TORCH_EMU_WORKERS host threads at once, which
//     makes atomics race for real), in the order of AMS_TORCH_EMU_ORDER: forward (default),
//     reverse or shuffle (seed AMS_TORCH_EMU_SEED); a kernel whose result depends on the order
//     of its blocks or threads is wrong on a GPU, and the tests run every order;
//   * the threads of a block are fibers (ucontext) on one host thread: each runs until it
//     reaches __syncthreads(), a warp collective, or its end; __syncthreads() releases when every
//     thread of the block waits at the same call site (threads that exited while others wait,
//     or waiting at different call sites, is reported as an error: undefined behaviour in CUDA);
//   * warp collectives (__activemask, __ballot_sync, __any_sync, __all_sync, __match_any_sync,
//     __shfl*_sync, __syncwarp) group the lanes of a warp (32 consecutive linear thread indices)
//     that call them with the same mask; __activemask() is the set of lanes that reach it
//     before no thread can go on (the converged lanes); a _sync call whose mask names a lane that
//     never comes is reported as an error;
//   * __shared__ variables are `static thread_local`: one copy per block in flight;
//   * atomics are std::atomic_ref operations (relaxed), fences are sequentially consistent.
// What it cannot show: timing of any kind (warps, occupancy, coalescing, bank conflicts), the
// device's math library (its ulps differ from the host libm's), the device compiler's
// floating-point contraction (nvcc fuses a*b+c into FMA by default; this build does not), out-
// of-bounds accesses (use compute-sanitizer on a GPU), register or local-memory limits (see the
// ptxas check), and dynamic shared memory (`extern __shared__`), which is not supported.
#pragma once

#include <sys/mman.h>
#include <ucontext.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <random>
#include <string>
#include <thread>
#include <tuple>
#include <type_traits>
#include <utility>
#include <vector>

#include "cuda_emulation_runtime.h"

// -- keywords -------------------------------------------------------------------------------------
#define __global__
#define __device__
#define __host__
#define __constant__
#define __managed__
#define __noinline__ __attribute__((noinline))
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __grid_constant__
#define __shared__ static thread_local

namespace ams_emu {
namespace detail {

enum class FiberState : uint8_t { kRunnable, kAtBarrier, kAtWarp, kDone };
enum class WarpOp : uint8_t { kActiveMask, kSyncWarp, kBallot, kAny, kAll, kMatchAny, kShfl, kShflUp, kShflDown,
                              kShflXor };

struct Fiber {
  ucontext_t ctx;
  FiberState state = FiberState::kRunnable;
  uint3 tid{0, 0, 0};
  unsigned linear = 0;
  const void* site = nullptr;  // __syncthreads call site
  WarpOp op = WarpOp::kActiveMask;
  unsigned mask = 0;
  uint64_t value = 0, result = 0;
  int param = 0, width = kWarpSize;
};

struct Block {
  uint3 block_idx{0, 0, 0};
  dim3 block_dim, grid_dim;
  const std::function<void()>* body = nullptr;
  std::vector<Fiber> fibers;
  ucontext_t scheduler;
  cudaError_t error = cudaSuccess;
  std::string detail;
  void fail(cudaError_t e, const std::string& what) {
    if (error == cudaSuccess) {
      error = e;
      detail = what;
    }
  }
};

inline thread_local Block* t_block = nullptr;
inline thread_local Fiber* t_fiber = nullptr;

// Fiber stacks of this host thread, reused by every block it runs (fiber i takes stack i), each
// with a guard page below it (an overflow faults instead of corrupting a neighbour).
constexpr size_t kStackBytes = 256 * 1024;

struct StackPool {
  std::vector<char*> stacks;
  size_t page = size_t(sysconf(_SC_PAGESIZE));
  char* get(size_t i) {
    while (stacks.size() <= i) {
      void* p = mmap(nullptr, kStackBytes + page, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE,
                     -1, 0);
      if (p == MAP_FAILED) return nullptr;
      mprotect(p, page, PROT_NONE);
      stacks.push_back(static_cast<char*>(p));
    }
    return stacks[i] + page;
  }
  ~StackPool() {
    for (char* s : stacks) munmap(s, kStackBytes + page);
  }
};

inline thread_local StackPool t_stacks;

inline void fiber_entry() {
  (*t_block->body)();
  t_fiber->state = FiberState::kDone;
  // returns to uc_link: the scheduler
}

inline void yield_to_scheduler() { swapcontext(&t_fiber->ctx, &t_block->scheduler); }

inline unsigned lane_of(const Fiber& f) { return f.linear % unsigned(kWarpSize); }

inline uint64_t shuffle_source(const Fiber& f, const Block&, const std::vector<Fiber>& warp, unsigned arrived,
                               unsigned base) {
  const int lane = int(lane_of(f));
  const int width = (f.width >= 1 && f.width <= kWarpSize) ? f.width : kWarpSize;
  const int seg = lane - lane % width;
  int src = lane;
  switch (f.op) {
    case WarpOp::kShfl: src = seg + ((f.param % width) + width) % width; break;
    case WarpOp::kShflUp: src = lane - f.param >= seg ? lane - f.param : lane; break;
    case WarpOp::kShflDown: src = lane + f.param < seg + width ? lane + f.param : lane; break;
    case WarpOp::kShflXor: {
      const int s = lane ^ f.param;
      src = (s >= seg && s < seg + width) ? s : lane;
      break;
    }
    default: break;
  }
  if (src < 0 || src >= kWarpSize || !(arrived >> src & 1u)) return f.value;  // an inactive source: own value
  return warp[base + unsigned(src)].value;
}

// Release the lanes of warp `w` waiting in collective `op` with mask `mask` (arrived: who came).
inline void release_group(Block& b, unsigned base, unsigned count, WarpOp op, unsigned mask, unsigned arrived) {
  std::vector<Fiber>& fs = b.fibers;
  for (unsigned l = 0; l < count; ++l) {
    Fiber& f = fs[base + l];
    if (f.state != FiberState::kAtWarp || f.op != op || f.mask != mask) continue;
    if (!(arrived >> l & 1u)) continue;
    uint64_t r = 0;
    switch (op) {
      case WarpOp::kActiveMask: r = arrived; break;
      case WarpOp::kSyncWarp: break;
      case WarpOp::kBallot:
      case WarpOp::kAny:
      case WarpOp::kAll: {
        unsigned votes = 0;
        for (unsigned k = 0; k < count; ++k)
          if ((arrived >> k & 1u) && fs[base + k].value != 0) votes |= 1u << k;
        r = op == WarpOp::kBallot ? votes : (op == WarpOp::kAny ? votes != 0 : votes == arrived);
        break;
      }
      case WarpOp::kMatchAny: {
        unsigned same = 0;
        for (unsigned k = 0; k < count; ++k)
          if ((arrived >> k & 1u) && fs[base + k].value == f.value) same |= 1u << k;
        r = same;
        break;
      }
      default: r = shuffle_source(f, b, fs, arrived, base); break;
    }
    f.result = r;
    f.state = FiberState::kRunnable;
  }
}

// Release warp groups, in three phases. 0: _sync groups whose every named lane has arrived (a mask
// naming a lane that exited or does not exist is an error, released at once). 1 (quiescence: no
// fiber can run): __activemask groups, the lanes that reached it. 2 (deadlock): _sync groups
// still missing a lane, as an error. Returns whether any lane was released.
inline bool release_warps(Block& b, int phase) {
  bool released = false;
  const unsigned n = unsigned(b.fibers.size());
  for (unsigned base = 0; base < n; base += unsigned(kWarpSize)) {
    const unsigned count = std::min(unsigned(kWarpSize), n - base);
    const unsigned exists = count == 32u ? 0xffffffffu : ((1u << count) - 1u);
    unsigned done = 0;
    for (unsigned l = 0; l < count; ++l)
      if (b.fibers[base + l].state == FiberState::kDone) done |= 1u << l;
    for (unsigned l = 0; l < count; ++l) {
      const Fiber& f = b.fibers[base + l];
      if (f.state != FiberState::kAtWarp) continue;
      const WarpOp op = f.op;
      const unsigned mask = f.mask;
      unsigned arrived = 0;
      for (unsigned k = 0; k < count; ++k) {
        const Fiber& g = b.fibers[base + k];
        if (g.state == FiberState::kAtWarp && g.op == op && g.mask == mask) arrived |= 1u << k;
      }
      if (op == WarpOp::kActiveMask) {
        if (phase != 1) continue;
      } else if (!(mask >> l & 1u)) {
        b.fail(cudaErrorIllegalInstruction, "a warp collective's mask does not name the calling lane");
      } else if ((mask & ~exists) != 0u || (mask & done) != 0u) {
        b.fail(cudaErrorIllegalInstruction,
               "a warp collective's mask names a lane that has exited or does not exist (undefined behaviour)");
      } else if ((arrived & mask) != mask) {
        if (phase != 2) continue;
        b.fail(cudaErrorIllegalInstruction,
               "deadlock: a warp collective (_sync) waits for a lane of its mask that never reaches it");
      }
      release_group(b, base, count, op, mask, arrived);
      released = true;
    }
  }
  return released;
}

inline std::vector<unsigned> schedule(unsigned n, int order, std::mt19937_64& rng) {
  std::vector<unsigned> idx(n);
  for (unsigned i = 0; i < n; ++i) idx[i] = i;
  if (order == 1) std::reverse(idx.begin(), idx.end());
  if (order == 2) std::shuffle(idx.begin(), idx.end(), rng);
  return idx;
}

// Run one block: every thread a fiber, passes over the runnable ones until all are done.
inline void run_block(Block& b, int order, std::mt19937_64& rng) {
  const unsigned bx = b.block_dim.x, by = b.block_dim.y;
  const unsigned n = b.block_dim.x * b.block_dim.y * b.block_dim.z;
  b.fibers.assign(n, Fiber{});
  for (unsigned i = 0; i < n; ++i) {
    Fiber& f = b.fibers[i];
    f.linear = i;
    f.tid = uint3{i % bx, (i / bx) % by, i / (bx * by)};
    char* stack = t_stacks.get(i);
    if (stack == nullptr) {
      b.fail(cudaErrorMemoryAllocation, "no memory for a fiber stack");
      return;
    }
    getcontext(&f.ctx);
    f.ctx.uc_stack.ss_sp = stack;
    f.ctx.uc_stack.ss_size = kStackBytes;
    f.ctx.uc_link = &b.scheduler;
    makecontext(&f.ctx, fiber_entry, 0);
  }
  Block* saved_block = t_block;
  Fiber* saved_fiber = t_fiber;
  t_block = &b;
  for (;;) {
    const std::vector<unsigned> pass = schedule(n, order, rng);
    for (unsigned i : pass) {
      Fiber& f = b.fibers[i];
      if (f.state != FiberState::kRunnable) continue;
      t_fiber = &f;
      swapcontext(&b.scheduler, &f.ctx);
    }
    if (release_warps(b, 0) || release_warps(b, 1)) continue;
    unsigned live = 0, waiting = 0;
    const void* site = nullptr;
    bool same_site = true;
    for (const Fiber& f : b.fibers) {
      if (f.state == FiberState::kDone) continue;
      ++live;
      if (f.state == FiberState::kAtBarrier) {
        ++waiting;
        if (site == nullptr) site = f.site;
        same_site = same_site && f.site == site;
      }
    }
    if (live == 0) break;
    if (waiting != live) {  // some wait in a warp collective that cannot complete
      release_warps(b, 2);
      continue;
    }
    if (live != n) {
      b.fail(cudaErrorIllegalInstruction,
             "__syncthreads() reached by some threads of a block after others exited (undefined behaviour)");
    } else if (!same_site) {
      b.fail(cudaErrorIllegalInstruction, "threads of a block wait at different __syncthreads() calls (divergent "
                                          "barrier: undefined behaviour)");
    }
    for (Fiber& f : b.fibers)  // release the barrier (after an error too, so that the block ends)
      if (f.state == FiberState::kAtBarrier) f.state = FiberState::kRunnable;
  }
  t_block = saved_block;
  t_fiber = saved_fiber;
}

inline int env_order() {
  const char* s = getenv("AMS_TORCH_EMU_ORDER");
  if (s == nullptr) return 0;
  if (strcmp(s, "reverse") == 0) return 1;
  if (strcmp(s, "shuffle") == 0) return 2;
  return 0;
}

inline std::string dims(dim3 d) {
  return "(" + std::to_string(d.x) + ", " + std::to_string(d.y) + ", " + std::to_string(d.z) + ")";
}

} // namespace detail

// One launch: `where` is "file:line kernel" of the launch site.
struct LaunchConfig {
  const char* where;
  dim3 grid, block;
  size_t shared;
  cudaStream_t stream;
  LaunchConfig(const char* w, dim3 g, dim3 b, size_t s = 0, cudaStream_t st = nullptr)
      : where(w), grid(g), block(b), shared(s), stream(st) {}
  template <class... A>
  auto operator()(A&&... args) const;
};

template <class... A>
struct PendingLaunch {
  LaunchConfig cfg;
  std::tuple<A...> args;
};

template <class... A>
auto LaunchConfig::operator()(A&&... args) const {
  return PendingLaunch<std::decay_t<A>...>{*this, std::tuple<std::decay_t<A>...>(std::forward<A>(args)...)};
}

// Check the configuration, then run every block (see the header comment). Errors go to
// cudaGetLastError(), as on the device.
inline void launch(const LaunchConfig& cfg, const void* kernel, const std::function<void()>& body) {
  using detail::dims;
  const std::string where = std::string(cfg.where) + ": ";
  const dim3 g = cfg.grid, b = cfg.block;
  const unsigned long long threads = 1ull * b.x * b.y * b.z;
  if (threads == 0 || threads > kMaxThreadsPerBlock || b.x > kMaxBlockDim[0] || b.y > kMaxBlockDim[1] ||
      b.z > kMaxBlockDim[2]) {
    set_error(cudaErrorInvalidConfiguration, where + "block " + dims(b) + " (at most 1024 threads, 1024 x 1024 x 64)");
    return;
  }
  if (g.x == 0 || g.y == 0 || g.z == 0 || g.x > kMaxGridDim[0] || g.y > kMaxGridDim[1] || g.z > kMaxGridDim[2]) {
    set_error(cudaErrorInvalidConfiguration, where + "grid " + dims(g) + " (1 .. 2^31-1 x 65535 x 65535)");
    return;
  }
  if (cfg.shared > dynamic_shared_limit(kernel)) {
    set_error(cudaErrorInvalidValue, where + std::to_string(cfg.shared) + " bytes of dynamic shared memory (limit " +
                                         std::to_string(dynamic_shared_limit(kernel)) + ")");
    return;
  }
  const unsigned long long blocks = 1ull * g.x * g.y * g.z;
  const int order = detail::env_order();
  const uint64_t seed = uint64_t(env_long("AMS_TORCH_EMU_SEED", 1));
  const long workers = std::min<long>(env_long("AMS_TORCH_EMU_WORKERS", 1), long(blocks));
  std::vector<unsigned long long> sequence;
  if (order != 0) {
    sequence.resize(blocks);
    for (unsigned long long i = 0; i < blocks; ++i) sequence[i] = order == 1 ? blocks - 1 - i : i;
    if (order == 2) {
      std::mt19937_64 rng(seed);
      std::shuffle(sequence.begin(), sequence.end(), rng);
    }
  }
  std::atomic<unsigned long long> next{0};
  std::vector<std::string> errors(size_t(workers > 0 ? workers : 1));
  std::vector<cudaError_t> codes(errors.size(), cudaSuccess);
  auto worker = [&](size_t w) {
    detail::Block blk;
    blk.block_dim = b;
    blk.grid_dim = g;
    blk.body = &body;
    std::mt19937_64 rng(seed + 7919 * w);
    for (;;) {
      const unsigned long long i = next.fetch_add(1);
      if (i >= blocks) break;
      const unsigned long long id = order == 0 ? i : sequence[i];
      blk.block_idx = uint3{unsigned(id % g.x), unsigned((id / g.x) % g.y), unsigned(id / (1ull * g.x * g.y))};
      detail::run_block(blk, order, rng);
      if (blk.error != cudaSuccess) {
        codes[w] = blk.error;
        errors[w] = "block " + std::to_string(id) + ": " + blk.detail;
        break;
      }
    }
  };
  if (workers <= 1) {
    worker(0);
  } else {
    std::vector<std::thread> pool;
    for (long w = 0; w < workers; ++w) pool.emplace_back(worker, size_t(w));
    for (std::thread& t : pool) t.join();
  }
  for (size_t w = 0; w < codes.size(); ++w)
    if (codes[w] != cudaSuccess) {
      set_error(codes[w], where + errors[w]);
      return;
    }
}

template <class... P, class... A>
void operator|(void (*kernel)(P...), PendingLaunch<A...>&& pending) {
  const std::function<void()> body = [&] { std::apply(kernel, pending.args); };
  launch(pending.cfg, reinterpret_cast<const void*>(kernel), body);
}

// -- inside a kernel ---------------------------------------------------------------------------
inline detail::Fiber& self() { return *detail::t_fiber; }

__attribute__((noinline)) inline void syncthreads() {
  detail::Fiber& f = self();
  f.site = __builtin_return_address(0);
  f.state = detail::FiberState::kAtBarrier;
  detail::yield_to_scheduler();
}

inline uint64_t warp_collective(detail::WarpOp op, unsigned mask, uint64_t value, int param = 0,
                                int width = kWarpSize) {
  detail::Fiber& f = self();
  f.op = op;
  f.mask = op == detail::WarpOp::kActiveMask ? 0u : mask;
  f.value = value;
  f.param = param;
  f.width = width;
  f.state = detail::FiberState::kAtWarp;
  detail::yield_to_scheduler();
  return f.result;
}

template <class T>
inline uint64_t to_bits(T v) {
  static_assert(sizeof(T) <= 8 && std::is_trivially_copyable<T>::value, "warp shuffles move values of <= 8 bytes");
  uint64_t bits = 0;
  memcpy(&bits, &v, sizeof(T));
  return bits;
}

template <class T>
inline T from_bits(uint64_t bits) {
  T v;
  memcpy(&v, &bits, sizeof(T));
  return v;
}

} // namespace ams_emu

#define threadIdx (::ams_emu::self().tid)
#define blockIdx (::ams_emu::detail::t_block->block_idx)
#define blockDim (::ams_emu::detail::t_block->block_dim)
#define gridDim (::ams_emu::detail::t_block->grid_dim)

inline constexpr int warpSize = 32;  // a constant, not a macro: host code's prop.warpSize keeps working

inline void __syncthreads() { ams_emu::syncthreads(); }
inline void __threadfence() { std::atomic_thread_fence(std::memory_order_seq_cst); }
inline void __threadfence_block() { std::atomic_thread_fence(std::memory_order_seq_cst); }
inline void __syncwarp(unsigned mask = 0xffffffffu) {
  ams_emu::warp_collective(ams_emu::detail::WarpOp::kSyncWarp, mask, 0);
}
inline unsigned __activemask() {
  return unsigned(ams_emu::warp_collective(ams_emu::detail::WarpOp::kActiveMask, 0, 0));
}
inline unsigned __ballot_sync(unsigned mask, int pred) {
  return unsigned(ams_emu::warp_collective(ams_emu::detail::WarpOp::kBallot, mask, pred != 0));
}
inline int __any_sync(unsigned mask, int pred) {
  return int(ams_emu::warp_collective(ams_emu::detail::WarpOp::kAny, mask, pred != 0));
}
inline int __all_sync(unsigned mask, int pred) {
  return int(ams_emu::warp_collective(ams_emu::detail::WarpOp::kAll, mask, pred != 0));
}
template <class T>
inline unsigned __match_any_sync(unsigned mask, T value) {
  return unsigned(ams_emu::warp_collective(ams_emu::detail::WarpOp::kMatchAny, mask, ams_emu::to_bits(value)));
}
template <class T>
inline T __shfl_sync(unsigned mask, T var, int src, int width = warpSize) {
  return ams_emu::from_bits<T>(
      ams_emu::warp_collective(ams_emu::detail::WarpOp::kShfl, mask, ams_emu::to_bits(var), src, width));
}
template <class T>
inline T __shfl_up_sync(unsigned mask, T var, unsigned delta, int width = warpSize) {
  return ams_emu::from_bits<T>(
      ams_emu::warp_collective(ams_emu::detail::WarpOp::kShflUp, mask, ams_emu::to_bits(var), int(delta), width));
}
template <class T>
inline T __shfl_down_sync(unsigned mask, T var, unsigned delta, int width = warpSize) {
  return ams_emu::from_bits<T>(
      ams_emu::warp_collective(ams_emu::detail::WarpOp::kShflDown, mask, ams_emu::to_bits(var), int(delta), width));
}
template <class T>
inline T __shfl_xor_sync(unsigned mask, T var, int lane_mask, int width = warpSize) {
  return ams_emu::from_bits<T>(
      ams_emu::warp_collective(ams_emu::detail::WarpOp::kShflXor, mask, ams_emu::to_bits(var), lane_mask, width));
}

// -- integer intrinsics ----------------------------------------------------------------------------
inline int __ffs(int x) { return __builtin_ffs(x); }
inline int __ffsll(long long x) { return __builtin_ffsll(x); }
inline int __popc(unsigned x) { return __builtin_popcount(x); }
inline int __popcll(unsigned long long x) { return __builtin_popcountll(x); }
inline int __clz(int x) { return x == 0 ? 32 : __builtin_clz(unsigned(x)); }
inline int __clzll(long long x) { return x == 0 ? 64 : __builtin_clzll((unsigned long long)x); }
inline unsigned __brev(unsigned x) {
  unsigned r = 0;
  for (int i = 0; i < 32; ++i) r |= ((x >> i) & 1u) << (31 - i);
  return r;
}

// -- atomics ---------------------------------------------------------------------------------------
#define AMS_EMU_ATOMIC_ADD(T)                                                                \
  inline T atomicAdd(T* address, T value) {                                                  \
    return std::atomic_ref<T>(*address).fetch_add(value, std::memory_order_relaxed);         \
  }                                                                                          \
  inline T atomicSub(T* address, T value) {                                                  \
    return std::atomic_ref<T>(*address).fetch_sub(value, std::memory_order_relaxed);         \
  }                                                                                          \
  inline T atomicExch(T* address, T value) {                                                 \
    return std::atomic_ref<T>(*address).exchange(value, std::memory_order_relaxed);          \
  }
AMS_EMU_ATOMIC_ADD(int)
AMS_EMU_ATOMIC_ADD(unsigned int)
AMS_EMU_ATOMIC_ADD(unsigned long long)
AMS_EMU_ATOMIC_ADD(float)
AMS_EMU_ATOMIC_ADD(double)
#undef AMS_EMU_ATOMIC_ADD

#define AMS_EMU_ATOMIC_INT(T)                                                                   \
  inline T atomicCAS(T* address, T compare, T value) {                                          \
    std::atomic_ref<T>(*address).compare_exchange_strong(compare, value);                       \
    return compare;                                                                             \
  }                                                                                             \
  inline T atomicMin(T* address, T value) {                                                     \
    std::atomic_ref<T> a(*address);                                                             \
    T old = a.load();                                                                           \
    while (value < old && !a.compare_exchange_weak(old, value)) {                               \
    }                                                                                           \
    return old;                                                                                 \
  }                                                                                             \
  inline T atomicMax(T* address, T value) {                                                     \
    std::atomic_ref<T> a(*address);                                                             \
    T old = a.load();                                                                           \
    while (value > old && !a.compare_exchange_weak(old, value)) {                               \
    }                                                                                           \
    return old;                                                                                 \
  }                                                                                             \
  inline T atomicAnd(T* address, T value) { return std::atomic_ref<T>(*address).fetch_and(value); } \
  inline T atomicOr(T* address, T value) { return std::atomic_ref<T>(*address).fetch_or(value); }   \
  inline T atomicXor(T* address, T value) { return std::atomic_ref<T>(*address).fetch_xor(value); }
AMS_EMU_ATOMIC_INT(int)
AMS_EMU_ATOMIC_INT(unsigned int)
AMS_EMU_ATOMIC_INT(unsigned long long)
AMS_EMU_ATOMIC_INT(long long)
#undef AMS_EMU_ATOMIC_INT

// -- loads and device math -------------------------------------------------------------------------
template <class T>
inline T __ldg(const T* p) { return *p; }
template <class T>
inline T __ldcg(const T* p) { return *p; }
template <class T>
inline T __ldca(const T* p) { return *p; }
template <class T>
inline T __ldcs(const T* p) { return *p; }
template <class T>
inline T __ldlu(const T* p) { return *p; }
template <class T>
inline void __stcg(T* p, T v) { *p = v; }
template <class T>
inline void __stcs(T* p, T v) { *p = v; }

inline float rsqrtf(float x) { return 1.0f / sqrtf(x); }
inline double rsqrt(double x) { return 1.0 / sqrt(x); }
inline float __fdividef(float a, float b) { return a / b; }
inline float fdividef(float a, float b) { return a / b; }
inline float __expf(float x) { return expf(x); }
inline float __logf(float x) { return logf(x); }
inline float __sinf(float x) { return sinf(x); }
inline float __cosf(float x) { return cosf(x); }
inline float __powf(float a, float b) { return powf(a, b); }
inline float __saturatef(float x) { return x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x); }
inline float __fmaf_rn(float a, float b, float c) { return fmaf(a, b, c); }
inline double __fma_rn(double a, double b, double c) { return fma(a, b, c); }
