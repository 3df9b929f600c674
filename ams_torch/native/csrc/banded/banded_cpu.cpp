// CPU kernel of the banded strand solve: op `ams_torch_cpu::solve_banded(blocks, rhs) -> x`.
//
//   blocks: (..., N, 4, 3, 3) float32/float64, blocks[..., i, k] = A[i, i-k] (see banded_cholesky.h
//           for exactly which entries are read); rhs: (..., N, 3), same dtype. x: (..., N, 3).
//
// Strands are independent. Threads (at::parallel_for) take contiguous ranges of strands; each
// thread solves W strands at once: it copies them into a per-thread scratch buffer in a
// strand-interleaved layout (value e of lane l at e*W + l), and runs the shared per-strand
// routine (banded_cholesky.h) on W-lane SIMD vectors (GCC/Clang vector extensions), factoring
// in place. The scratch is allocated once per thread and reused across calls; nothing is
// allocated per strand. The last group of a range is padded with copies of a real strand.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <memory>

#include "banded/banded_cholesky.h"
#include "banded/banded_simd.h"
#include "common/interleave.h"
#include "common/thread_scratch.h"

namespace ams_torch {
namespace banded {

template <class T>
static void solve_strands(const T* blocks, const T* rhs, T* x, int64_t S, int64_t N) {
  using V = typename LaneVec<T>::type;
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  const int64_t E = N * kRowElems; // matrix values per strand
  const int64_t R = N * kRhsElems; // rhs values per strand
  const int64_t groups = (S + W - 1) / W;
  // Enough strands per task that thread start-up is amortised (~64k values of work).
  const int64_t grain = std::max<int64_t>(1, (int64_t(1) << 16) / std::max<int64_t>(1, (E + R) * W));

  at::parallel_for(0, groups, grain, [&](int64_t g_begin, int64_t g_end) {
    T* sa = static_cast<T*>(ams_torch::thread_scratch(size_t(E + R) * W * sizeof(T), "solver"));
    T* sb = sa + E * W;
    const Lanes<V, T> a{sa, W};
    const Lanes<V, T> b{sb, W};
    for (int64_t g = g_begin; g < g_end; ++g) {
      const int64_t s0 = g * W;
      const T* pa[W];
      const T* pb[W];
      for (int64_t l = 0; l < W; ++l) {
        const int64_t src = std::min(s0 + l, S - 1); // pad the last group with a real strand
        pa[l] = blocks + src * E;
        pb[l] = rhs + src * R;
      }
      interleave<T, W>(sa, pa, E);
      interleave<T, W>(sb, pb, R);
      solve_strand<V, T>(a, b, N);
      const int64_t lanes = std::min<int64_t>(W, S - s0);
      T* px[W];
      for (int64_t l = 0; l < lanes; ++l) px[l] = x + (s0 + l) * R;
      deinterleave<T, W>(px, sb, R, lanes);
    }
  });
}

at::Tensor solve_banded_cpu(const at::Tensor& blocks, const at::Tensor& rhs) {
  TORCH_CHECK(blocks.dim() >= 4 && blocks.size(-1) == 3 && blocks.size(-2) == 3 && blocks.size(-3) == kBand + 1,
              "ams_torch_cpu::solve_banded: blocks must have shape (..., N, 4, 3, 3), got ", blocks.sizes());
  TORCH_CHECK(rhs.dim() == blocks.dim() - 2 && rhs.size(-1) == 3 &&
                  rhs.sizes().slice(0, rhs.dim() - 1) == blocks.sizes().slice(0, blocks.dim() - 3),
              "ams_torch_cpu::solve_banded: rhs must have shape (..., N, 3) matching blocks ", blocks.sizes(),
              ", got ", rhs.sizes());
  TORCH_CHECK(blocks.device().is_cpu() && rhs.device().is_cpu(), "ams_torch_cpu::solve_banded: CPU tensors expected");
  TORCH_CHECK(blocks.scalar_type() == rhs.scalar_type(),
              "ams_torch_cpu::solve_banded: blocks and rhs must have the same dtype, got ", blocks.scalar_type(),
              " and ", rhs.scalar_type());
  const at::Tensor b = blocks.contiguous();
  const at::Tensor r = rhs.contiguous();
  at::Tensor x = at::empty(rhs.sizes(), rhs.options().memory_format(at::MemoryFormat::Contiguous));
  const int64_t N = blocks.size(-4);
  if (x.numel() == 0) return x;
  const int64_t S = r.numel() / (N * kRhsElems);
  AT_DISPATCH_FLOATING_TYPES(r.scalar_type(), "ams_torch_cpu::solve_banded", [&] {
    solve_strands<scalar_t>(b.const_data_ptr<scalar_t>(), r.const_data_ptr<scalar_t>(), x.mutable_data_ptr<scalar_t>(), S,
                            N);
  });
  return x;
}

} // namespace banded
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def("solve_banded(Tensor blocks, Tensor rhs) -> Tensor");
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("solve_banded", &ams_torch::banded::solve_banded_cpu);
}
