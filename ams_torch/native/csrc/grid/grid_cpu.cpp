// CPU kernels of the block-sparse hair–hair grid: ops `ams_torch_cpu::{p2g, pressure, g2p}`
// (shapes in grid.h and ams_torch/stages/hair_hair/native.py). The arithmetic is grid.h's, shared
// with CUDA. Work and storage follow the blocks the hair occupies: nothing here visits R^3 cells.
//
// Parallelism (at::parallel_for), chosen so that results do not depend on the thread count:
//   * P2G: every particle marks the blocks its stencils touch (parallel; each mark writes the same
//     byte), then per scene the marked blocks get slots in block order (the torch definition's
//     order) and only those slots are zeroed. The scatter buckets particles by x-slab of kSlab
//     cells (stable counting sort): a particle of slab s writes only face planes
//     [s kSlab - 1, (s + 1) kSlab] along x, so slabs s and s + 2 never share a face: even slabs
//     are scattered in parallel, then odd slabs, and each face sums its contributions in one fixed
//     order whatever the number of threads. (Per-thread pools would cost a pool of zeroing and
//     reduction per thread, atomics a varying order.)
//   * pressure: per used slot (parallel) its neighbour slots, which of its 64 cells are active
//     and their entries. The Jacobi sweeps visit only the active cells of "awake" slots: at
//     first those with a pushing cell (src > 0), then every neighbour of a slot whose phi became
//     non-zero. A slot that is not awake has src <= 0 everywhere and zero phi in itself and its
//     neighbours, where a sweep would give max(0, src) = 0: the values are exactly those of
//     sweeping every cell. A scene without a pushing cell never sweeps (phi stays exactly 0).
//     Double-buffered, parallel over the awake slots. The active cells are counted per scene, to
//     flag the overflow of the torch path's active-cell list as that path does.
//   * field (per used slot: pic u alone where phi cannot reach) and G2P (per batch of particles,
//     grid_simd.h's lanes): independent, parallel.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <tuple>
#include <vector>

#include "common/thread_scratch.h"
#include "grid/bits.h"
#include "grid/grid.h"
#include "grid/grid_simd.h"

namespace ams_torch {
namespace grid {
namespace {

constexpr int64_t kSlab = 4; // cells per x-slab of the P2G colouring (>= 2)
constexpr int64_t kParticleGrain = 1024;
constexpr int64_t kSlotGrain = 16;

// The large temporaries of one op call, carved from the calling thread's scratch
// (common/thread_scratch.h: kept across calls), not allocated per call: at R = 128 they are
// megabytes, which malloc maps fresh and the kernel then page-faults in, every frame.
class Carve {
 public:
  explicit Carve(size_t bytes, const char* what)
      : base_(static_cast<char*>(ams_torch::thread_scratch(bytes + 64 * kParts, what))) {}
  template <class U>
  U* take(int64_t n) {
    U* out = reinterpret_cast<U*>(base_ + used_);
    used_ += (size_t(n) * sizeof(U) + 63) / 64 * 64;
    return out;
  }
  template <class U>
  static size_t bytes(int64_t n) {
    return (size_t(n) * sizeof(U) + 63) / 64 * 64;
  }
  static constexpr int kParts = 8; // at most this many take() per call

 private:
  char* base_;
  size_t used_ = 0;
};

void set_mark(uint8_t* p) {
#if defined(__GNUC__)
  __atomic_store_n(p, uint8_t(1), __ATOMIC_RELAXED); // other threads may store the same 1
#else
  *p = 1;
#endif
}

// Bit l: the three lower faces of cell l of `slot` (in the block itself) have mass > eps, which
// every active cell needs (the cheap part of grid.h's cell_entry test).
template <class T>
uint64_t lower_faces_massive(const T* faces, int64_t slot, T eps) {
  const T* f = faces + slot * 3 * kBlockCells * 2;
#if AMS_GRID_SIMD
  return simd::lower_faces_massive(f, eps);
#endif
  uint64_t bits = 0;
  for (int l = 0; l < kBlockCells; ++l) {
    const bool all = f[2 * l] > eps && f[2 * (kBlockCells + l)] > eps && f[2 * (2 * kBlockCells + l)] > eps;
    bits |= uint64_t(all) << l;
  }
  return bits;
}

void check_common(const char* op, const at::Tensor& t, const char* name, at::ScalarType dtype) {
  TORCH_CHECK(t.device().is_cpu(), "ams_torch_cpu::", op, ": ", name, " must be a CPU tensor");
  TORCH_CHECK(t.scalar_type() == dtype, "ams_torch_cpu::", op, ": ", name, " must be ", dtype, ", got ",
              t.scalar_type());
}

void check_particles(const char* op, const at::Tensor& x, const at::Tensor& v, const at::Tensor& frame,
                     const at::Tensor& origin, double cell_size, int64_t r) {
  TORCH_CHECK(x.dim() == 3 && x.size(2) == 3, "ams_torch_cpu::", op, ": x must be (B, P, 3), got ", x.sizes());
  TORCH_CHECK(v.sizes() == x.sizes(), "ams_torch_cpu::", op, ": v must be ", x.sizes(), ", got ", v.sizes());
  TORCH_CHECK(frame.dim() == 3 && frame.size(0) == x.size(0) && frame.size(1) == 6 && frame.size(2) == 3,
              "ams_torch_cpu::", op, ": frame must be (B, 6, 3), got ", frame.sizes());
  TORCH_CHECK(origin.dim() == 1 && origin.size(0) == 3, "ams_torch_cpu::", op, ": origin must be (3,)");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cpu::", op, ": need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(blocks_per_axis(r) * blocks_per_axis(r) * blocks_per_axis(r) < (int64_t(1) << 31),
              "ams_torch_cpu::", op, ": resolution too large (at most 2^31 - 1 blocks)");
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "ams_torch_cpu::", op, ": float32 or float64 only");
  check_common(op, x, "x", dtype);
  check_common(op, v, "v", dtype);
  check_common(op, frame, "frame", dtype);
  check_common(op, origin, "origin", dtype);
}

void check_int(const char* op, const at::Tensor& t, const char* name, at::IntArrayRef sizes) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kInt && t.sizes() == sizes, "ams_torch_cpu::", op,
              ": ", name, " must be a CPU int32 tensor of shape ", sizes, ", got ", t.scalar_type(), " ", t.sizes());
}

// Per-particle passes run over batches of kLanes particles of one scene (the SIMD lanes of
// grid_simd.h, or one particle at a time without them): batch t of scene b covers particles
// [t kLanes, min((t + 1) kLanes, P)).
#if AMS_GRID_SIMD
template <class T>
constexpr int lanes_of() {
  return simd::Lanes<T>::W;
}
#else
template <class T>
constexpr int lanes_of() {
  return 1;
}
#endif

// First pass of P2G over particles [q0, q0 + n) of scene b: head-frame coordinates (head: 6 per
// particle), x-slab of each particle, and the marks of the blocks its stencils touch.
template <class T>
void p2g_mark(const T* x, const T* v, const T* fr, const T* origin, T h, int64_t r, int64_t nb, int64_t q0, int n,
              T* head, int32_t* slab, uint8_t* mark) {
#if AMS_GRID_SIMD
  using V = simd::VecT<T>;
  using I = simd::IntT<T>;
  V xs[3], vs[3], xl[3], vl[3];
  for (int lane = 0; lane < simd::Lanes<T>::W; ++lane) {
    const int64_t q = q0 + (lane < n ? lane : n - 1);
    for (int a = 0; a < 3; ++a) {
      xs[a][lane] = x[3 * q + a];
      vs[a][lane] = v[3 * q + a];
    }
  }
  simd::to_head<T>(fr, xs, vs, xl, vl);
  I first[3], last[3], inside;
  simd::batch_blocks<T>(xl, origin, h, r, first, last, inside);
  const V cx = simd::Lanes<T>::floor((xl[0] - origin[0]) / h);
  for (int lane = 0; lane < n; ++lane) {
    T* hd = head + 6 * (q0 + lane);
    for (int a = 0; a < 3; ++a) {
      hd[a] = xl[a][lane];
      hd[3 + a] = vl[a][lane];
    }
    T c = cx[lane];
#else
  for (int lane = 0; lane < n; ++lane) {
    T* hd = head + 6 * (q0 + lane);
    to_head(fr, x + 3 * (q0 + lane), v + 3 * (q0 + lane), hd, hd + 3);
    int64_t first_s[3], last_s[3];
    const bool in = particle_blocks(hd, origin, h, r, first_s, last_s);
    T c = grid_floor(cell_coord(hd, origin, h, 0));
#endif
    if (!(c >= T(0))) c = T(0); // also NaN
    if (c > T(r - 1)) c = T(r - 1);
    slab[q0 + lane] = int32_t(int64_t(c) / kSlab);
#if AMS_GRID_SIMD
    if (!inside[lane]) continue;
    const int64_t f0 = first[0][lane], f1 = first[1][lane], f2 = first[2][lane];
    const int64_t l0 = last[0][lane], l1 = last[1][lane], l2 = last[2][lane];
#else
    if (!in) continue;
    const int64_t f0 = first_s[0], f1 = first_s[1], f2 = first_s[2], l0 = last_s[0], l1 = last_s[1], l2 = last_s[2];
#endif
    for (int64_t i = f0; i <= l0; ++i)
      for (int64_t j = f1; j <= l1; ++j)
        for (int64_t k = f2; k <= l2; ++k) set_mark(mark + (i * nb + j) * nb + k);
  }
}

// Scatter of particles order[i0 .. i0 + n) (indices within scene b) into the scene's pool.
template <class T>
void p2g_scatter(const T* head, const T* m, const int32_t* order, int64_t i0, int n, const T* origin, T h, int64_t r,
                 int64_t nb, const int32_t* table, T* faces) {
#if AMS_GRID_SIMD
  using V = simd::VecT<T>;
  V xl[3];
  for (int lane = 0; lane < simd::Lanes<T>::W; ++lane) {
    const T* hd = head + 6 * order[i0 + (lane < n ? lane : n - 1)];
    for (int a = 0; a < 3; ++a) xl[a][lane] = hd[a];
  }
  simd::Batch<T> bt;
  simd::batch_stencil<T>(xl, origin, h, r, nb, table, n, bt);
  // a face's (mass, momentum) pair in one 2-lane vector: the two adds of grid.h's p2g_particle
  typedef T Pair __attribute__((vector_size(2 * sizeof(T)), may_alias));
  for (int lane = 0; lane < n; ++lane) {
    const int32_t p = order[i0 + lane];
    const T* vl = head + 6 * p + 3;
    const T mp = m[p];
    for (int c = 0; c < 3; ++c) {
      const Pair mv = {mp, mp * vl[c]};
      for (int k = 0; k < 8; ++k) {
        const int64_t f = bt.face[c][k][lane];
        if (f < 0) continue;
        *reinterpret_cast<Pair*>(faces + 2 * f) += bt.w[c][k][lane] * mv;
      }
    }
  }
#else
  const auto add = [](T* ptr, T value) { *ptr += value; };
  for (int lane = 0; lane < n; ++lane) {
    const int32_t p = order[i0 + lane];
    const T* hd = head + 6 * p;
    p2g_particle(hd, hd + 3, m[p], origin, h, r, nb, table, faces, add);
  }
#endif
}

template <class T>
void p2g_impl(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int32_t* table,
              int32_t* blocks, int32_t* count, int64_t B, int64_t P, int64_t r, int64_t K, double cell_size) {
  const T h = T(cell_size);
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  const int64_t pool = K * 3 * kBlockCells * 2; // values of one scene's faces
  const int64_t slabs = (r + kSlab - 1) / kSlab;
  constexpr int W = lanes_of<T>();
  const int64_t batches = (P + W - 1) / W;
  Carve scratch(Carve::bytes<T>(B * P * 6) + Carve::bytes<int32_t>(B * P) * 2 + Carve::bytes<uint8_t>(B * nb3),
                "grid P2G");
  T* head = scratch.take<T>(B * P * 6);
  int32_t* slab = scratch.take<int32_t>(B * P);
  int32_t* order = scratch.take<int32_t>(B * P);
  uint8_t* mark = scratch.take<uint8_t>(B * nb3);
  std::memset(mark, 0, size_t(B * nb3));
  at::parallel_for(0, B * batches, kParticleGrain / W, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t b = t / batches, first = (t % batches) * W;
      p2g_mark(x + 3 * b * P, v + 3 * b * P, frame + 18 * b, origin, h, r, nb, first,
               int(std::min<int64_t>(W, P - first)), head + 6 * b * P, slab + b * P, mark + b * nb3);
    }
  });
  // per scene: slots in block order, particles sorted by slab
  std::vector<int64_t> start(size_t(B * (slabs + 1)));
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const uint8_t* mk = mark + b * nb3;
      int32_t* tb = table + b * nb3;
      int32_t* bl = blocks + b * K;
      int64_t n = 0;
      for (int64_t id = 0; id < nb3; ++id) {
        if (!mk[id]) {
          tb[id] = -1;
          continue;
        }
        tb[id] = n < K ? int32_t(n) : -1;
        if (n < K) bl[n] = int32_t(id);
        ++n;
      }
      const int64_t used = std::min(n, K);
      std::fill(bl + used, bl + K, -1);
      count[b] = int32_t(n);
      int64_t* st = start.data() + b * (slabs + 1);
      std::fill(st, st + slabs + 1, 0);
      for (int64_t p = 0; p < P; ++p) ++st[slab[b * P + p] + 1];
      for (int64_t s = 0; s < slabs; ++s) st[s + 1] += st[s];
      std::vector<int64_t> fill(st, st + slabs);
      for (int64_t p = 0; p < P; ++p) order[b * P + fill[slab[b * P + p]]++] = int32_t(p);
    }
  });
  at::parallel_for(0, B * K, kSlotGrain, [&](int64_t u0, int64_t u1) { // zero the used slots' faces
    for (int64_t u = u0; u < u1; ++u)
      if (u % K < std::min<int64_t>(count[u / K], K))
        std::fill(faces + u * 3 * kBlockCells * 2, faces + (u + 1) * 3 * kBlockCells * 2, T(0));
  });
  for (int64_t colour = 0; colour < 2; ++colour) {
    const int64_t per_scene = (slabs - colour + 1) / 2; // slabs colour, colour + 2, ...
    at::parallel_for(0, B * per_scene, 1, [&](int64_t t0, int64_t t1) {
      for (int64_t t = t0; t < t1; ++t) {
        const int64_t b = t / per_scene;
        const int64_t s = colour + 2 * (t % per_scene);
        const int64_t* st = start.data() + b * (slabs + 1);
        for (int64_t i = st[s]; i < st[s + 1]; i += W)
          p2g_scatter(head + 6 * b * P, m + b * P, order + b * P, i,
                      int(std::min<int64_t>(W, st[s + 1] - i)), origin, h, r, nb, table + b * nb3, faces + b * pool);
      }
    });
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> p2g_cpu(const at::Tensor& x, const at::Tensor& v,
                                                                   const at::Tensor& m, const at::Tensor& frame,
                                                                   const at::Tensor& origin, double cell_size,
                                                                   int64_t resolution, int64_t capacity) {
  check_particles("p2g", x, v, frame, origin, cell_size, resolution);
  TORCH_CHECK(m.dim() == 2 && m.size(0) == x.size(0) && m.size(1) == x.size(1),
              "ams_torch_cpu::p2g: m must be (B, P), got ", m.sizes());
  check_common("p2g", m, "m", x.scalar_type());
  const int64_t B = x.size(0), P = x.size(1), r = resolution, K = capacity;
  const int64_t nb = blocks_per_axis(r);
  TORCH_CHECK(K >= 1 && K <= nb * nb * nb, "ams_torch_cpu::p2g: capacity must be in [1, ", nb * nb * nb,
              "] blocks, got ", K);
  TORCH_CHECK(P < (int64_t(1) << 31), "ams_torch_cpu::p2g: at most 2^31 - 1 particles per scene");
  at::Tensor faces = at::empty({B, K, 3, kBlockCells, 2}, x.options());
  at::Tensor table = at::empty({B, nb * nb * nb}, x.options().dtype(at::kInt));
  at::Tensor blocks = at::empty({B, K}, x.options().dtype(at::kInt));
  at::Tensor count = at::empty({B}, x.options().dtype(at::kInt));
  if (B == 0) return {faces, table, blocks, count};
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), mc = m.contiguous(), fc = frame.contiguous(),
                   oc = origin.contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_cpu::p2g", [&] {
    p2g_impl<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(), mc.const_data_ptr<scalar_t>(),
                       fc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(), faces.mutable_data_ptr<scalar_t>(),
                       table.mutable_data_ptr<int32_t>(), blocks.mutable_data_ptr<int32_t>(),
                       count.mutable_data_ptr<int32_t>(), B, P, r, K, cell_size);
  });
  return {faces, table, blocks, count};
}

template <class T>
void pressure_impl(const T* faces, const int32_t* table, const int32_t* blocks, const int32_t* count, T rho0, T dt,
                   T* phi_out, T* field, bool* overflow, int64_t B, int64_t r, int64_t K,
                   double cell_size, int64_t iterations, double omega, double stiffness, double pic,
                   int64_t active_capacity) {
  const PressureConsts<T> q = pressure_consts<T>(cell_size, rho0, dt, omega, stiffness, pic);
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  const int64_t pool = K * 3 * kBlockCells; // faces of one scene
  std::vector<int32_t> scene; // the used slots of every scene, numbered u = first[b] + slot
  const std::vector<int64_t> first = used_slots(count, B, K, &scene);
  const int64_t U = first[B];
  // Slots >= count[b] of phi and field are not written (as P2G leaves them in faces): nothing
  // reads them (G2P reaches the pool through the table), and zeroing them would cost the whole
  // capacity, 4x the hair's blocks by default, every frame.
  for (int64_t b = 0; b < B; ++b) overflow[b] = count[b] > K; // the blocks P2G left out
  if (U == 0) return;
  std::vector<int32_t> nbr(size_t(U * 6));
  std::vector<uint8_t> awake(static_cast<size_t>(U), 0);
  std::vector<uint64_t> active(static_cast<size_t>(U), 0); // bit l: cell l of the slot is active
  // the sweeps' two phi buffers: phi_out is the one the last sweep writes, the other is scratch
  Carve scratch(Carve::bytes<T>(iterations > 0 ? U * kBlockCells * kEntry : 0) + Carve::bytes<T>(B * K * kBlockCells),
                "grid pressure");
  T* const entries = scratch.take<T>(iterations > 0 ? U * kBlockCells * kEntry : 0);
  T* const phi_other = scratch.take<T>(B * K * kBlockCells);
  T* const phi_a = iterations % 2 == 0 ? phi_out : phi_other;
  T* const phi_b = iterations % 2 == 0 ? phi_other : phi_out;
  at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
    for (int64_t u = u0; u < u1; ++u) {
      const int64_t b = scene[u], slot = u - first[b];
      int32_t* nu = nbr.data() + 6 * u;
      slot_neighbours(blocks[b * K + slot], nb, table + b * nb3, nu);
      std::fill(phi_a + (b * K + slot) * kBlockCells, phi_a + (b * K + slot + 1) * kBlockCells, T(0));
      std::fill(phi_b + (b * K + slot) * kBlockCells, phi_b + (b * K + slot + 1) * kBlockCells, T(0));
      if (iterations == 0) continue;
      const T* fs = faces + b * pool * 2;
      T* e = entries + u * kBlockCells * kEntry;
      bool pushes = false;
      uint64_t bits = 0;
      for (uint64_t cand = lower_faces_massive(fs, slot, q.eps); cand; cand &= cand - 1) {
        const int l = lowest_bit(cand);
        if (cell_entry(fs, slot, l, nu, q, e + kEntry * l)) {
          bits |= uint64_t(1) << l;
          pushes = pushes || e[kEntry * l] > T(0);
        }
      }
      active[u] = bits;
      awake[u] = pushes;
    }
  });
  if (iterations > 0) {
    std::vector<int64_t> listed(static_cast<size_t>(B), 0); // active cells: the torch path lists them
    for (int64_t u = 0; u < U; ++u) listed[scene[u]] += popcount(active[u]);
    for (int64_t b = 0; b < B; ++b) overflow[b] = overflow[b] || listed[b] > active_capacity;
    std::vector<int64_t> list;
    for (int64_t u = 0; u < U; ++u)
      if (awake[u]) list.push_back(u);
    std::vector<uint8_t> live(static_cast<size_t>(U), 0);
    for (int64_t it = 0; it < iterations && !list.empty(); ++it) {
      const T* src = it % 2 == 0 ? phi_a : phi_b;
      T* dst = it % 2 == 0 ? phi_b : phi_a;
      const int64_t n = int64_t(list.size());
      at::parallel_for(0, n, kSlotGrain, [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i) {
          const int64_t u = list[i], b = scene[u], slot = u - first[b];
          const T* ps = src + b * K * kBlockCells;
          T* pd = dst + (b * K + slot) * kBlockCells;
          const T* e = entries + u * kBlockCells * kEntry;
          bool any = false;
          for (uint64_t bits = active[u]; bits; bits &= bits - 1) { // inactive cells keep phi = 0
            const int l = lowest_bit(bits);
            const T t = sweep_cell(ps, slot, l, nbr.data() + 6 * u, e + kEntry * l, q.one_minus_omega);
            pd[l] = t;
            any = any || t != T(0); // NaN counts: it spreads as in the full sweeps
          }
          live[u] = any;
        }
      });
      wake_neighbours(list, n, live, awake, nbr.data(), first.data(), scene.data()); // of the slots that hold phi
    }
  }
  const T* phi = iterations % 2 == 0 ? phi_a : phi_b;
  at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
    for (int64_t u = u0; u < u1; ++u) {
      const int64_t b = scene[u], slot = u - first[b];
      const T* fs = faces + b * pool * 2;
      const T* ps = phi + b * K * kBlockCells;
      T* out = field + b * pool + slot * 3 * kBlockCells;
      // phi is 0 outside the awake slots: where neither this slot nor its x-, y-, z- neighbours
      // are awake, du = -(0 / h) h^3 / M = -0 on every face and the field is pic u exactly
      bool quiet = !awake[u];
      for (int d = 0; d < 6 && quiet; d += 2) quiet = nbr[6 * u + d] < 0 || !awake[first[b] + nbr[6 * u + d]];
      if (quiet) {
        const T* f = fs + slot * 3 * kBlockCells * 2;
#if AMS_GRID_SIMD
        simd::quiet_field(f, q.pic, out);
#else
        for (int i = 0; i < 3 * kBlockCells; ++i) out[i] = f[2 * i] > T(0) ? q.pic * (f[2 * i + 1] / f[2 * i]) : T(0);
#endif
        continue;
      }
      for (int c = 0; c < 3; ++c)
        for (int l = 0; l < kBlockCells; ++l)
          out[c * kBlockCells + l] = face_field(fs, ps, slot, c, l, nbr.data() + 6 * u, q);
    }
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> pressure_cpu(const at::Tensor& faces, const at::Tensor& table,
                                                            const at::Tensor& blocks, const at::Tensor& count,
                                                            const at::Tensor& target, const at::Tensor& dt,
                                                            double cell_size, int64_t resolution, int64_t iterations,
                                                            double omega, double stiffness, double pic,
                                                            int64_t active_capacity) {
  const int64_t r = resolution;
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cpu::pressure: need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(faces.dim() == 5 && faces.size(2) == 3 && faces.size(3) == kBlockCells && faces.size(4) == 2,
              "ams_torch_cpu::pressure: faces must be (B, K, 3, 64, 2), got ", faces.sizes());
  const int64_t B = faces.size(0), K = faces.size(1), nb = blocks_per_axis(r);
  check_int("pressure", table, "table", {B, nb * nb * nb});
  check_int("pressure", blocks, "blocks", {B, K});
  check_int("pressure", count, "count", {B});
  TORCH_CHECK(target.dim() == 0 && dt.dim() == 0, "ams_torch_cpu::pressure: target and dt must be 0-d tensors");
  TORCH_CHECK(iterations >= 0, "ams_torch_cpu::pressure: iterations must be >= 0");
  const auto dtype = faces.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "ams_torch_cpu::pressure: float32 or float64 only");
  check_common("pressure", faces, "faces", dtype);
  check_common("pressure", target, "target", dtype);
  check_common("pressure", dt, "dt", dtype);
  at::Tensor phi = at::empty({B, K, kBlockCells}, faces.options());
  at::Tensor field = at::empty({B, K, 3, kBlockCells}, faces.options());
  at::Tensor overflow = at::empty({B}, faces.options().dtype(at::kBool));
  if (B == 0) return {phi, field, overflow};
  const at::Tensor fc = faces.contiguous(), tc = table.contiguous(), bc = blocks.contiguous(), cc = count.contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "ams_torch_cpu::pressure", [&] {
    pressure_impl<scalar_t>(fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(), bc.const_data_ptr<int32_t>(),
                            cc.const_data_ptr<int32_t>(), target.item<scalar_t>(), dt.item<scalar_t>(),
                            phi.mutable_data_ptr<scalar_t>(), field.mutable_data_ptr<scalar_t>(),
                            overflow.mutable_data_ptr<bool>(), B, r, K, cell_size, iterations, omega, stiffness, pic,
                            active_capacity);
  });
  return {phi, field, overflow};
}

// G2P of particles [q0, q0 + n) of one scene (x, v, xo, vo, free_p: that scene's).
template <class T>
void g2p_batch(const T* fr, const T* x, const T* v, const T* field, const int32_t* table, int64_t nb, const T* origin,
               T h, int64_t r, T pic, const bool* free, int64_t N, T dt, int64_t q0, int n, T* xo, T* vo) {
#if AMS_GRID_SIMD
  using V = simd::VecT<T>;
  using I = simd::IntT<T>;
  V xs[3], vs[3], xl[3], vl[3];
  I fm{};
  for (int lane = 0; lane < simd::Lanes<T>::W; ++lane) {
    const int64_t q = q0 + (lane < n ? lane : n - 1);
    for (int a = 0; a < 3; ++a) {
      xs[a][lane] = x[3 * q + a];
      vs[a][lane] = v[3 * q + a];
    }
    fm[lane] = free[q % N] ? -1 : 0;
  }
  simd::to_head<T>(fr, xs, vs, xl, vl);
  simd::Batch<T> bt;
  simd::batch_stencil<T>(xl, origin, h, r, nb, table, n, bt);
  V dv[3];
  simd::batch_change<T>(bt, field, vl, fm, pic, dv);
  const V dx[3] = {dt * dv[0], dt * dv[1], dt * dv[2]};
  V ox[3], ov[3];
  for (int i = 0; i < 3; ++i) {
    ox[i] = xs[i] + (fr[3 * i] * dx[0] + fr[3 * i + 1] * dx[1] + fr[3 * i + 2] * dx[2]);
    ov[i] = vs[i] + (fr[3 * i] * dv[0] + fr[3 * i + 1] * dv[1] + fr[3 * i + 2] * dv[2]);
  }
  for (int lane = 0; lane < n; ++lane)
    for (int a = 0; a < 3; ++a) {
      xo[3 * (q0 + lane) + a] = ox[a][lane];
      vo[3 * (q0 + lane) + a] = ov[a][lane];
    }
#else
  for (int lane = 0; lane < n; ++lane) {
    const int64_t q = q0 + lane;
    g2p_particle(fr, x + 3 * q, v + 3 * q, field, table, nb, origin, h, r, pic, free[q % N], dt, xo + 3 * q,
                 vo + 3 * q);
  }
#endif
}

template <class T>
void g2p_impl(const T* x, const T* v, const T* field, const int32_t* table, const T* frame, const T* origin,
              const bool* free, T dt, T* xo, T* vo, int64_t B, int64_t P, int64_t N, int64_t r, int64_t K,
              double cell_size, double pic) {
  const T h = T(cell_size), pict = T(pic);
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  constexpr int W = lanes_of<T>();
  const int64_t batches = (P + W - 1) / W;
  at::parallel_for(0, B * batches, kParticleGrain / W, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t b = t / batches, first = (t % batches) * W;
      g2p_batch(frame + 18 * b, x + 3 * b * P, v + 3 * b * P, field + b * K * 3 * kBlockCells, table + b * nb3, nb,
                origin, h, r, pict, free, N, dt, first, int(std::min<int64_t>(W, P - first)), xo + 3 * b * P,
                vo + 3 * b * P);
    }
  });
}

std::tuple<at::Tensor, at::Tensor> g2p_cpu(const at::Tensor& x, const at::Tensor& v, const at::Tensor& field,
                                           const at::Tensor& table, const at::Tensor& frame, const at::Tensor& origin,
                                           const at::Tensor& free, const at::Tensor& dt, double cell_size,
                                           int64_t resolution, double pic) {
  check_particles("g2p", x, v, frame, origin, cell_size, resolution);
  const int64_t B = x.size(0), P = x.size(1), r = resolution, nb = blocks_per_axis(r);
  TORCH_CHECK(field.dim() == 4 && field.size(0) == B && field.size(2) == 3 && field.size(3) == kBlockCells,
              "ams_torch_cpu::g2p: field must be (B, K, 3, 64), got ", field.sizes());
  const int64_t K = field.size(1);
  check_common("g2p", field, "field", x.scalar_type());
  check_int("g2p", table, "table", {B, nb * nb * nb});
  check_common("g2p", dt, "dt", x.scalar_type());
  TORCH_CHECK(dt.dim() == 0, "ams_torch_cpu::g2p: dt must be a 0-d tensor");
  TORCH_CHECK(free.dim() == 1 && free.size(0) > 0 && P % free.size(0) == 0 && free.scalar_type() == at::kBool &&
                  free.device().is_cpu(),
              "ams_torch_cpu::g2p: free must be a CPU bool tensor (N,) with N dividing P, got ", free.sizes());
  at::Tensor xo = at::empty({B, P, 3}, x.options());
  at::Tensor vo = at::empty({B, P, 3}, x.options());
  if (B * P == 0) return {xo, vo};
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), fc = field.contiguous(), tc = table.contiguous(),
                   frc = frame.contiguous(), oc = origin.contiguous(), freec = free.contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_cpu::g2p", [&] {
    g2p_impl<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(), fc.const_data_ptr<scalar_t>(),
                       tc.const_data_ptr<int32_t>(), frc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(),
                       freec.const_data_ptr<bool>(), dt.item<scalar_t>(), xo.mutable_data_ptr<scalar_t>(),
                       vo.mutable_data_ptr<scalar_t>(), B, P, free.size(0), r, K, cell_size, pic);
  });
  return {xo, vo};
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def("p2g(Tensor x, Tensor v, Tensor m, Tensor frame, Tensor origin, float cell_size, int resolution, "
        "int capacity) -> (Tensor, Tensor, Tensor, Tensor)");
  m.def("pressure(Tensor faces, Tensor table, Tensor blocks, Tensor count, Tensor target, Tensor dt, "
        "float cell_size, int resolution, int iterations, float omega, float stiffness, float pic, int active_capacity) "
        "-> (Tensor, Tensor, Tensor)");
  m.def("g2p(Tensor x, Tensor v, Tensor field, Tensor table, Tensor frame, Tensor origin, Tensor free, Tensor dt, "
        "float cell_size, int resolution, float pic) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("p2g", &ams_torch::grid::p2g_cpu);
  m.impl("pressure", &ams_torch::grid::pressure_cpu);
  m.impl("g2p", &ams_torch::grid::g2p_cpu);
}
