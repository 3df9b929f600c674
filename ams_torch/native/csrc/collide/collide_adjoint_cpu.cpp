// CPU kernel of the collision stage's adjoint: op `ams_torch_cpu::collide_adjoint` (schema and
// shapes in collide_binding.h; arithmetic in collide_adjoint.h, shared with CUDA).
//
// As the forward (collide_cpu.cpp): tasks of (scene, group of W strands) by at::parallel_for, each
// copying its strands' x, v, output adjoints (and the rest shape and edge lengths for
// follow-the-leader) into per-thread scratch in the strand-interleaved layout, running the adjoint
// on W-lane vectors, and copying x̄, v̄ and each strand's pose adjoints out (summed over strands on
// the torch side: deterministic, no atomics).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <tuple>
#include <vector>

#include "banded/banded_simd.h"
#include "collide/collide_adjoint.h"
#include "collide/collide_binding.h"
#include "common/interleave.h"
#include "common/thread_scratch.h"

namespace ams_torch {
namespace collide {
namespace {

constexpr const char* kOp = "ams_torch_cpu::collide_adjoint";

template <class T>
void run_adjoint(const CollideArgs<T>& args, const CollideSettings& cfg, const T* gx, const T* gv, T* gxo, T* gvo,
                 T* gcol, T* ghead) {
  using V = typename banded::LaneVec<T>::type;
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  const int64_t B = args.scenes, S = args.strands, N = args.particles, C = args.count;
  const int rounds = cfg.inextensibility ? cfg.rounds : 0;
  std::vector<Prepared<T>> prepared(size_t(std::max<int64_t>(1, B * C)));
  for (int64_t b = 0; b < B; ++b)
    for (int64_t c = 0; c < C; ++c) prepare_collider(args.colliders[c], b, prepared[b * C + c]);
  // per lane: history 6N (1 + 2 rounds), x̄ 3N, v̄ 3N, x̄' 3N, λ 3N, rest 3N, edge lengths N − 1, pinned 1
  const int64_t hist = 6 * N * (1 + 2 * rounds);
  const int64_t oxb = hist, ovb = oxb + 3 * N, oxn = ovb + 3 * N, olam = oxn + 3 * N, orest = olam + 3 * N,
                oedge = orest + 3 * N, opin = oedge + N - 1, total = opin + 1;
  const int64_t groups = (S + W - 1) / W;
  at::parallel_for(0, B * groups, 1, [&](int64_t t_begin, int64_t t_end) {
    T* sc = static_cast<T*>(ams_torch::thread_scratch(size_t(total * W) * sizeof(T), "collision adjoint"));
    const StageAdjoint<V, T> w{Lanes<V, T>{sc, W}, Lanes<V, T>{sc + oxb * W, W}, Lanes<V, T>{sc + ovb * W, W},
                               Lanes<V, T>{sc + oxn * W, W}, Lanes<V, T>{sc + olam * W, W}};
    const Lanes<V, T> rest{sc + orest * W, W}, edge{sc + oedge * W, W};
    std::vector<V> acc(size_t(std::max<int64_t>(1, C * kPoseGrads)));
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
      gather(args.x, 3 * N, 3 * N, b * S, 0);
      gather(args.v, 3 * N, 3 * N, b * S, 3 * N);
      gather(gx, 3 * N, 3 * N, b * S, oxb);
      gather(gv, 3 * N, 3 * N, b * S, ovb);
      if (rounds > 0) {
        gather(args.rest_positions, 3 * N, 3 * N, 0, orest);
        gather(args.edge_rest_length, N - 1, N - 1, 0, oedge);
      }
      T* pin = sc + opin * W;
      for (int64_t l = 0; l < W; ++l)
        pin[l] = T(std::min<int64_t>(std::max<int64_t>(args.num_pinned[strand[l]], 0), N));
      const V pinned = *reinterpret_cast<const V*>(pin);
      const T* head = args.head_rotation + 9 * (args.head_scenes == 1 ? 0 : b);
      const V zero = frame::splat<V, T>(T(0));
      for (auto& a : acc) a = zero;
      V headb[9];
      for (auto& h : headb) h = zero;
      collision_stage_adjoint(w, rest, edge, N, pinned, prepared.data() + b * C, int(C), cfg, head, acc.data(), headb);
      T* dst[W];
      for (int64_t l = 0; l < lanes; ++l) dst[l] = gxo + (b * S + s0 + l) * 3 * N;
      banded::deinterleave<T, W>(dst, sc + oxb * W, 3 * N, lanes);
      for (int64_t l = 0; l < lanes; ++l) dst[l] = gvo + (b * S + s0 + l) * 3 * N;
      banded::deinterleave<T, W>(dst, sc + ovb * W, 3 * N, lanes);
      for (int64_t l = 0; l < lanes; ++l) {
        T* col = gcol + (b * S + s0 + l) * C * kPoseGrads;
        for (int64_t k = 0; k < C * kPoseGrads; ++k) col[k] = LaneAccess<V, T>::get(acc[size_t(k)], int(l));
        T* hd = ghead + (b * S + s0 + l) * 9;
        for (int e = 0; e < 9; ++e) hd[e] = LaneAccess<V, T>::get(headb[e], int(l));
      }
    }
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> collide_adjoint_cpu(
    const at::Tensor& x, const at::Tensor& v, at::TensorList model, const at::Tensor& head, at::TensorList tensors,
    at::TensorList poses, c10::IntArrayRef ints, c10::ArrayRef<double> floats, double dt, int64_t rounds,
    bool inextensibility, double ftl_damping, const at::Tensor& x_bar, const at::Tensor& v_bar) {
  const CollideInputs in =
      check_collide_inputs(kOp, x, v, model, head, tensors, poses, ints, floats, dt, rounds, inextensibility,
                           ftl_damping);
  TORCH_CHECK(in.x.device().is_cpu(), kOp, ": CPU tensors expected");
  const auto [gx, gv] = check_adjoint_inputs(kOp, in, x_bar, v_bar, kMaxPushout);
  const auto opts = in.x.options().memory_format(at::MemoryFormat::Contiguous);
  at::Tensor gxo = at::empty(in.x.sizes(), opts), gvo = at::empty(in.x.sizes(), opts);
  at::Tensor gcol = at::zeros({in.scenes, in.strands, in.count, kPoseGrads}, opts);
  at::Tensor ghead = at::zeros({in.scenes, in.strands, 9}, opts);
  if (in.scenes == 0 || in.strands == 0) return {gxo, gvo, gcol, ghead};
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), kOp, [&] {
    run_adjoint<scalar_t>(collide_args<scalar_t>(in), in.settings, gx.const_data_ptr<scalar_t>(),
                          gv.const_data_ptr<scalar_t>(), gxo.mutable_data_ptr<scalar_t>(),
                          gvo.mutable_data_ptr<scalar_t>(), gcol.mutable_data_ptr<scalar_t>(),
                          ghead.mutable_data_ptr<scalar_t>());
  });
  return {gxo, gvo, gcol, ghead};
}

} // namespace
} // namespace collide
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::collide::kCollideAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("collide_adjoint", &ams_torch::collide::collide_adjoint_cpu);
}
