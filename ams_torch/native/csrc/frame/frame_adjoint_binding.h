// Torch side of the differentiable frame ops, shared by the CPU kernel (frame_adjoint_cpu.cpp) and
// the CUDA binding (frame_adjoint_cuda_binding.cpp): validation, the adjoint outputs, raw pointers.
// Never included by CUDA sources (it needs torch headers).
//
// Op schemas (both backends; the Python op ams_torch::frame_dynamics_diff in
// ams_torch/sim/native_grad.py documents shapes and units):
//   frame_posed(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor poses, <settings>)
//               -> (Tensor, Tensor)      (<settings>: AMS_FRAME_SETTINGS of frame.h)
//     the frame of `frame` (frame_binding.h: state, external force and model alike) with the M + 1
//     substep head poses given: poses (P, M + 1, 12), P = 1 or the number of scenes, each pose R
//     row-major then t; returns the new (x, v).
//   frame_adjoint(<the arguments of frame_posed>, Tensor x_bar, Tensor v_bar) -> Tensor[]
//     x_bar, v_bar (..., S, N, 3): adjoints of frame_posed's outputs. Returns the adjoints
//     [x (..., S, N, 3), v, ghost_rest, external_force (like x, or an empty tensor without one),
//      mass (B, S, N), drag (B, S, N), edge (B, S, N-1), bend (B, S, N-2), torsion (B, S, N-3),
//      integrity (B, S, N), angular (B, S, N-1), poses (B, S, M+1, 12), sag_offset (like x),
//      the non-Hookean transition, breaking point and soft ratio (B, S, 3)], B the flattened scenes:
//     the per-strand arrays are per scene (the caller sums over scenes and strands as the
//     inputs broadcast).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>

#include <vector>

#include "frame/frame_adjoint.h"
#include "frame/frame_binding.h"

namespace ams_torch {
namespace frame {

constexpr const char* kFramePosedSchema =
    "frame_posed(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor poses" AMS_FRAME_SETTINGS_SCHEMA
    ") -> (Tensor, Tensor)";
constexpr const char* kFrameAdjointSchema =
    "frame_adjoint(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor poses" AMS_FRAME_SETTINGS_SCHEMA
    ", Tensor x_bar, Tensor v_bar) -> Tensor[]";

enum AdjointIndex {
  kXBar, kVBar, kGhostBar, kExtBar, kMassBar, kDragBar, kEdgeBar, kBendBar, kTorsionBar, kIntegrityBar, kAngularBar,
  kPoseBar, kSagBar, kLawBar, kAdjointCount
};

// Validated inputs: the frame's (check_frame_inputs) and the substep poses, contiguous.
struct PosedInputs {
  FrameInputs frame;
  at::Tensor poses; // (P, M + 1, 12)
  int64_t pose_scenes = 1;
};

inline PosedInputs check_posed_inputs(const char* op, at::TensorList state, const std::optional<at::Tensor>& ext,
                                      at::TensorList model, const at::Tensor& poses AMS_FRAME_SETTINGS_PARAMS) {
  TORCH_CHECK(substeps >= 1, op, ": substeps must be >= 1, got ", substeps);
  TORCH_CHECK(poses.dim() == 3 && poses.size(1) == substeps + 1 && poses.size(2) == kPoseElems, op,
              ": poses must have shape (P, substeps + 1, 12), got ", poses.sizes());
  TORCH_CHECK(angular_reaction || !angular, op, ": the one-particle angular form has no native adjoint");
  // the frame's own checks, with the first and last substep poses as the frame's two poses
  const at::Tensor p = poses.contiguous();
  const int64_t P = p.size(0);
  std::vector<at::Tensor> ends;
  for (int64_t k : {int64_t(0), substeps}) {
    const at::Tensor pk = p.select(1, k);
    const at::Tensor t = pk.slice(1, 9, 12);
    ends.push_back(pk.slice(1, 0, 9).reshape({P, 3, 3}));
    ends.push_back(t);
    ends.push_back(t);
  }
  PosedInputs in;
  in.frame = check_frame_inputs(op, state, ext, model, ends AMS_FRAME_SETTINGS_ARGS, false, -1);
  TORCH_CHECK(p.scalar_type() == state[kX].scalar_type(), op, ": poses must be ", state[kX].scalar_type());
  in.poses = p;
  in.pose_scenes = P;
  return in;
}

// The adjoint outputs (see the schema), allocated (zeros where a kernel may leave entries unset).
inline std::vector<at::Tensor> adjoint_outputs(const PosedInputs& in) {
  const FrameInputs& f = in.frame;
  const at::Tensor& x = f.state[kX];
  const auto opts = x.options().memory_format(at::MemoryFormat::Contiguous);
  const int64_t B = f.scenes, S = f.strands, N = f.particles, M = f.settings.substeps;
  std::vector<at::Tensor> out(kAdjointCount);
  out[kXBar] = at::empty(x.sizes(), opts);
  out[kVBar] = at::empty(x.sizes(), opts);
  out[kGhostBar] = at::empty(x.sizes(), opts);
  out[kExtBar] = f.external_force.has_value() ? at::empty(x.sizes(), opts) : at::empty({0}, opts);
  out[kMassBar] = at::empty({B, S, N}, opts);
  out[kDragBar] = at::empty({B, S, N}, opts);
  out[kEdgeBar] = at::empty({B, S, N - 1}, opts);
  out[kBendBar] = at::empty({B, S, N - 2}, opts);
  out[kTorsionBar] = at::empty({B, S, N - 3}, opts);
  out[kIntegrityBar] = at::zeros({B, S, N}, opts);
  out[kAngularBar] = at::zeros({B, S, N - 1}, opts);
  out[kPoseBar] = at::empty({B, S, M + 1, kPoseElems}, opts);
  out[kSagBar] = at::empty(x.sizes(), opts);
  out[kLawBar] = at::empty({B, S, 3}, opts);
  return out;
}

inline void check_adjoint_seeds(const char* op, const PosedInputs& in, const at::Tensor& xb, const at::Tensor& vb) {
  const at::Tensor& x = in.frame.state[kX];
  check_shape(op, xb, "x_bar", x.sizes());
  check_shape(op, vb, "v_bar", x.sizes());
  TORCH_CHECK(xb.scalar_type() == x.scalar_type() && vb.scalar_type() == x.scalar_type(), op,
              ": x_bar and v_bar must be ", x.scalar_type());
  TORCH_CHECK(xb.device() == x.device() && vb.device() == x.device(), op, ": x_bar and v_bar must be on ", x.device());
}

// Raw pointers of the adjoint outputs and seeds.
template <class T>
struct AdjointPointers {
  const T *xb_in, *vb_in;
  T *xb, *vb, *gb, *extb, *massb, *dragb, *stiffb[3], *integrityb, *angularb, *poseb, *sagb, *lawb;
};

template <class T>
AdjointPointers<T> adjoint_pointers(std::vector<at::Tensor>& out, const at::Tensor& xb, const at::Tensor& vb) {
  AdjointPointers<T> p{};
  p.xb_in = xb.const_data_ptr<T>();
  p.vb_in = vb.const_data_ptr<T>();
  p.xb = out[kXBar].mutable_data_ptr<T>();
  p.vb = out[kVBar].mutable_data_ptr<T>();
  p.gb = out[kGhostBar].mutable_data_ptr<T>();
  p.extb = out[kExtBar].numel() > 0 ? out[kExtBar].mutable_data_ptr<T>() : nullptr;
  p.massb = out[kMassBar].mutable_data_ptr<T>();
  p.dragb = out[kDragBar].mutable_data_ptr<T>();
  p.stiffb[0] = out[kEdgeBar].mutable_data_ptr<T>();
  p.stiffb[1] = out[kBendBar].mutable_data_ptr<T>();
  p.stiffb[2] = out[kTorsionBar].mutable_data_ptr<T>();
  p.integrityb = out[kIntegrityBar].mutable_data_ptr<T>();
  p.angularb = out[kAngularBar].mutable_data_ptr<T>();
  p.poseb = out[kPoseBar].mutable_data_ptr<T>();
  p.sagb = out[kSagBar].mutable_data_ptr<T>();
  p.lawb = out[kLawBar].mutable_data_ptr<T>();
  return p;
}

} // namespace frame
} // namespace ams_torch
