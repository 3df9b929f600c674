// CPU kernel of the fused collision stage: op `ams_torch_cpu::collide` (schema and shapes
// in collide_binding.h; arithmetic in collide.h, shared with CUDA).
//
// Tasks of (scene, group of W strands) run by at::parallel_for, W the SIMD width of
// banded_simd.h; a task copies its strands' x, v (and rest shape and edge lengths for
// follow-the-leader) into per-thread scratch in the strand-interleaved layout, runs the whole
// stage on W-lane vectors (the mesh grid is read lane by lane), and copies x, v out. The colliders'
// per-scene values (pose, offsets, geometry) are prepared once per call.
//
// Like every source of the CPU library, this one is compiled without floating-point contraction
// (-ffp-contract=off, ams_torch/native/build.py: no fused multiply-add): contact is decided by the
// sign of σ, and particles pushed out sit at σ ≈ 0, so σ and the normals are computed with the
// torch definition's own roundings (grid_sample's trilinear sum included) rather than one ulp away.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <tuple>
#include <vector>

#include "banded/banded_simd.h"
#include "collide/collide.h"
#include "collide/collide_binding.h"
#include "common/interleave.h"
#include "common/thread_scratch.h"

namespace ams_torch {
namespace collide {
namespace {

constexpr const char* kOp = "ams_torch_cpu::collide";

template <class T>
void run_collide(const CollideArgs<T>& args, const CollideSettings& cfg, T* xo, T* vo) {
  using V = typename banded::LaneVec<T>::type;
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  const int64_t B = args.scenes, S = args.strands, N = args.particles, C = args.count;
  std::vector<Prepared<T>> prepared(size_t(std::max<int64_t>(1, B * C)));
  for (int64_t b = 0; b < B; ++b)
    for (int64_t c = 0; c < C; ++c) prepare_collider(args.colliders[c], b, prepared[b * C + c]);
  // per lane: x 3N, v 3N, rest 3N, edge lengths N − 1, pinned count 1
  const int64_t ox = 0, ov = 3 * N, orest = 6 * N, oedge = 9 * N, opin = 10 * N - 1, total = 10 * N;
  const int64_t groups = (S + W - 1) / W;
  at::parallel_for(0, B * groups, 1, [&](int64_t t_begin, int64_t t_end) {
    T* sc = static_cast<T*>(ams_torch::thread_scratch(size_t(total * W) * sizeof(T), "collision"));
    const Lanes<V, T> x{sc + ox * W, W}, v{sc + ov * W, W}, rest{sc + orest * W, W}, edge{sc + oedge * W, W};
    for (int64_t task = t_begin; task < t_end; ++task) {
      const int64_t b = task / groups, s0 = (task % groups) * W;
      const int64_t lanes = std::min<int64_t>(W, S - s0);
      int64_t strand[W];
      for (int64_t l = 0; l < W; ++l) strand[l] = std::min(s0 + l, S - 1); // pad with a real strand
      auto gather = [&](const T* base, int64_t per_strand, int64_t stride, int64_t first, int64_t offset) {
        const T* src[W];
        for (int64_t l = 0; l < W; ++l) src[l] = base + (first + strand[l]) * stride;
        banded::interleave<T, W>(sc + offset * W, src, per_strand);
      };
      gather(args.x, 3 * N, 3 * N, b * S, ox);
      gather(args.v, 3 * N, 3 * N, b * S, ov);
      if (cfg.inextensibility && cfg.rounds > 0) {
        gather(args.rest_positions, 3 * N, 3 * N, 0, orest);
        gather(args.edge_rest_length, N - 1, N - 1, 0, oedge);
      }
      T* pin = sc + opin * W;
      for (int64_t l = 0; l < W; ++l)
        pin[l] = T(std::min<int64_t>(std::max<int64_t>(args.num_pinned[strand[l]], 0), N));
      const V pinned = *reinterpret_cast<const V*>(pin);
      const T* head = args.head_rotation + 9 * (args.head_scenes == 1 ? 0 : b);
      collision_stage(x, v, rest, edge, N, pinned, prepared.data() + b * C, int(C), cfg, head);
      T* dst[W];
      for (int64_t l = 0; l < lanes; ++l) dst[l] = xo + (b * S + s0 + l) * 3 * N;
      banded::deinterleave<T, W>(dst, sc + ox * W, 3 * N, lanes);
      for (int64_t l = 0; l < lanes; ++l) dst[l] = vo + (b * S + s0 + l) * 3 * N;
      banded::deinterleave<T, W>(dst, sc + ov * W, 3 * N, lanes);
    }
  });
}

std::tuple<at::Tensor, at::Tensor> collide_cpu(const at::Tensor& x, const at::Tensor& v, at::TensorList model,
                                               const at::Tensor& head, at::TensorList tensors, at::TensorList poses,
                                               c10::IntArrayRef ints, c10::ArrayRef<double> floats, double dt,
                                               int64_t rounds, bool inextensibility, double ftl_damping) {
  const CollideInputs in =
      check_collide_inputs(kOp, x, v, model, head, tensors, poses, ints, floats, dt, rounds, inextensibility,
                           ftl_damping);
  TORCH_CHECK(in.x.device().is_cpu(), kOp, ": CPU tensors expected");
  const auto opts = in.x.options().memory_format(at::MemoryFormat::Contiguous);
  at::Tensor xo = at::empty(in.x.sizes(), opts), vo = at::empty(in.x.sizes(), opts);
  if (in.scenes == 0 || in.strands == 0) return {xo, vo};
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), kOp, [&] {
    run_collide<scalar_t>(collide_args<scalar_t>(in), in.settings, xo.mutable_data_ptr<scalar_t>(),
                          vo.mutable_data_ptr<scalar_t>());
  });
  return {xo, vo};
}

} // namespace
} // namespace collide
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::collide::kCollideSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("collide", &ams_torch::collide::collide_cpu);
}
