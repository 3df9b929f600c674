// CPU kernels of the differentiable frame: ops `ams_torch_cpu::frame_posed` (the fused
// frame with its substep poses given) and `frame_adjoint` (its vector-Jacobian product;
// frame_adjoint.h, shared with CUDA). Schemas and shapes: frame_adjoint_binding.h.
//
// As the forward kernel (frame_cpu.cpp): tasks of (scene, group of W strands) run by
// at::parallel_for, W the SIMD width (8 float / 4 double strands with 32-byte vectors); a task
// copies its strands' inputs into a per-thread scratch in the strand-interleaved layout (value e of
// lane l at e·W + l), runs the per-strand routine on W-lane vectors, and copies the results out.
// The adjoint's scratch adds the states of the M + 1 substep starts and the adjoint arrays
// (about (6 M + 95) N W values: 28 KB per group of 8 float strands at N = 32, M = 1).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

#include "banded/banded_simd.h"
#include "frame/frame_adjoint.h"
#include "frame/frame_adjoint_binding.h"
#include "frame/strand_scratch_cpu.h"
#include "common/interleave.h"
#include "common/thread_scratch.h"

namespace ams_torch {
namespace frame {
namespace {

// The forward's strand layout, then the adjoint's arrays (the forward only uses the part before hist_x).
struct AdjointLayout : StrandLayout {
  int64_t hist_x, hist_v, xb, vb, xb_new, vb_new, lam, ya, yb, wb, vpb, gb, extb, massb, dragb, integrityb;
  int64_t stiffb[3], angularb, poseb, sagb, lawb;
  AdjointLayout(int64_t n, int64_t m) : StrandLayout(n) {
    hist_x = take(3 * n * (m + 1));
    hist_v = take(3 * n * (m + 1));
    for (int64_t* f : {&xb, &vb, &xb_new, &vb_new, &lam, &ya, &yb, &wb, &vpb, &gb, &extb}) *f = take(3 * n);
    for (int64_t* f : {&massb, &dragb, &integrityb}) *f = take(n);
    for (int k = 0; k < 3; ++k) stiffb[k] = take(n - 1 - k);
    angularb = take(n - 1);
    poseb = take(int64_t(kPoseElems) * (m + 1));
    sagb = take(3 * n);
    lawb = take(3);
  }
};

using banded::deinterleave;
using banded::interleave;

// Forward (ap == nullptr: x', v' into out_x, out_v) or adjoint (ap: the adjoints) of every strand.
template <class T>
void run_posed(const FrameArgs<T>& args, const FrameSettings& cfg, const T* poses, int64_t pose_scenes, T* out_x,
               T* out_v, const AdjointPointers<T>* ap) {
  using V = typename banded::LaneVec<T>::type;
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  const int64_t B = args.scenes, S = args.strands, N = args.particles, M = cfg.substeps;
  const Material<T> mat{{args.gravity[0], args.gravity[1], args.gravity[2]}, *args.transition, *args.breaking,
                        *args.soft_ratio};
  const AdjointLayout lay(N, M);
  const int64_t groups = (S + W - 1) / W;
  const bool has_ext = args.external_force != nullptr;
  const size_t bytes = size_t((ap ? lay.total : lay.hist_x) * W) * sizeof(T);

  at::parallel_for(0, B * groups, 1, [&](int64_t t_begin, int64_t t_end) {
    T* sc = static_cast<T*>(ams_torch::thread_scratch(bytes, "frame adjoint"));
    auto view = [&](int64_t offset) { return Lanes<V, T>{sc + offset * W, W}; };
    Strand<V, T> st;
    bind_strand(st, sc, lay, N, has_ext);
    Adjoint<V, T> adj;
    if (ap) {
      adj.hist_x = view(lay.hist_x);
      adj.hist_v = view(lay.hist_v);
      adj.xb = view(lay.xb);
      adj.vb = view(lay.vb);
      adj.xb_new = view(lay.xb_new);
      adj.vb_new = view(lay.vb_new);
      adj.lam = view(lay.lam);
      adj.ya = view(lay.ya);
      adj.yb = view(lay.yb);
      adj.wb = view(lay.wb);
      adj.vpb = view(lay.vpb);
      adj.gb = view(lay.gb);
      adj.extb = view(lay.extb);
      adj.massb = view(lay.massb);
      adj.dragb = view(lay.dragb);
      adj.integrityb = view(lay.integrityb);
      for (int k = 0; k < 3; ++k) adj.stiffb[k] = view(lay.stiffb[k]);
      adj.angularb = view(lay.angularb);
      adj.poseb = view(lay.poseb);
      adj.sagb = view(lay.sagb);
      adj.lawb = view(lay.lawb);
    }

    for (int64_t task = t_begin; task < t_end; ++task) {
      const int64_t b = task / groups, s0 = (task % groups) * W;
      const int64_t lanes = std::min<int64_t>(W, S - s0);
      int64_t strand[W];
      for (int64_t l = 0; l < W; ++l) strand[l] = std::min(s0 + l, S - 1); // pad with a real strand
      gather_strands(args, cfg, lay, sc, b, strand, st);
      const T* scene_poses = poses + (pose_scenes == 1 ? 0 : b) * (M + 1) * kPoseElems;
      T* dst[W];
      auto scatter = [&](T* base, int64_t per_strand, int64_t offset) {
        for (int64_t l = 0; l < lanes; ++l) dst[l] = base + (b * S + s0 + l) * per_strand;
        deinterleave<T, W>(dst, sc + offset * W, per_strand, lanes);
      };
      if (ap == nullptr) {
        strand_frame(st, mat, cfg, scene_poses);
        scatter(out_x, 3 * N, lay.x);
        scatter(out_v, 3 * N, lay.v);
        continue;
      }
      gather_scene_array<T, W>(sc, lay.xb, ap->xb_in, b, strand, S, N);
      gather_scene_array<T, W>(sc, lay.vb, ap->vb_in, b, strand, S, N);
      strand_frame_adjoint(st, adj, mat, cfg, scene_poses);
      scatter(ap->xb, 3 * N, lay.xb);
      scatter(ap->vb, 3 * N, lay.vb);
      scatter(ap->gb, 3 * N, lay.gb);
      if (has_ext) scatter(ap->extb, 3 * N, lay.extb);
      scatter(ap->massb, N, lay.massb);
      scatter(ap->dragb, N, lay.dragb);
      for (int k = 0; k < 3; ++k) scatter(ap->stiffb[k], N - 1 - k, lay.stiffb[k]);
      scatter(ap->integrityb, N, lay.integrityb);
      scatter(ap->angularb, N - 1, lay.angularb);
      scatter(ap->poseb, (M + 1) * kPoseElems, lay.poseb);
      scatter(ap->sagb, 3 * N, lay.sagb);
      scatter(ap->lawb, 3, lay.lawb);
    }
  });
}

constexpr const char* kPosedOp = "ams_torch_cpu::frame_posed";
constexpr const char* kAdjointOp = "ams_torch_cpu::frame_adjoint";

std::tuple<at::Tensor, at::Tensor> frame_posed_cpu(at::TensorList state, const std::optional<at::Tensor>& ext,
                                                   at::TensorList model,
                                                       const at::Tensor& poses AMS_FRAME_SETTINGS_PARAMS) {
  const PosedInputs in = check_posed_inputs(kPosedOp, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS);
  TORCH_CHECK(in.frame.state[kX].device().is_cpu(), kPosedOp, ": CPU tensors expected");
  at::Tensor x, v;
  std::tie(x, v) = frame_outputs(in.frame);
  if (in.frame.scenes > 0 && in.frame.strands > 0) {
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), kPosedOp, [&] {
      run_posed<scalar_t>(frame_args<scalar_t>(in.frame), in.frame.settings, in.poses.const_data_ptr<scalar_t>(),
                          in.pose_scenes, x.mutable_data_ptr<scalar_t>(), v.mutable_data_ptr<scalar_t>(), nullptr);
    });
  }
  return {x, v};
}

std::vector<at::Tensor> frame_adjoint_cpu(at::TensorList state, const std::optional<at::Tensor>& ext,
                                          at::TensorList model, const at::Tensor& poses AMS_FRAME_SETTINGS_PARAMS,
                                              const at::Tensor& x_bar, const at::Tensor& v_bar) {
  const PosedInputs in = check_posed_inputs(kAdjointOp, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS);
  TORCH_CHECK(in.frame.state[kX].device().is_cpu(), kAdjointOp, ": CPU tensors expected");
  check_adjoint_seeds(kAdjointOp, in, x_bar, v_bar);
  const at::Tensor xb = x_bar.contiguous(), vb = v_bar.contiguous();
  std::vector<at::Tensor> out = adjoint_outputs(in);
  if (in.frame.scenes > 0 && in.frame.strands > 0) {
    AT_DISPATCH_FLOATING_TYPES(xb.scalar_type(), kAdjointOp, [&] {
      const AdjointPointers<scalar_t> ap = adjoint_pointers<scalar_t>(out, xb, vb);
      run_posed<scalar_t>(frame_args<scalar_t>(in.frame), in.frame.settings, in.poses.const_data_ptr<scalar_t>(),
                          in.pose_scenes, nullptr, nullptr, &ap);
    });
  }
  return out;
}

} // namespace
} // namespace frame
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::frame::kFramePosedSchema);
  m.def(ams_torch::frame::kFrameAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("frame_posed", &ams_torch::frame::frame_posed_cpu);
  m.impl("frame_adjoint", &ams_torch::frame::frame_adjoint_cpu);
}
