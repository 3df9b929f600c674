// Torch side of the fused frame op, shared by the CPU kernel (frame_cpu.cpp) and the CUDA
// binding (frame_cuda_binding.cpp): argument validation and the raw-pointer FrameArgs of
// frame.h. Never included by CUDA sources (it needs torch headers).
//
// Op schema (both backends; the Python op ams_torch::frame_dynamics in ams_torch/sim/native.py
// documents shapes and units):
//   frame(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor[] poses, <settings>,
//         bool hermite, int assemble_substep) -> (Tensor, Tensor)
//   <settings>: float dt, int substeps, float ftl_damping, int integrity_model, bool angular, ...:
//            the X-macro AMS_FRAME_SETTINGS of frame.h (every frame op takes them in its order)
//   state:  [x, v, ghost_rest, sag_offset], each (..., S, N, 3) (the leading dims are the scenes)
//   model:  [rest_positions (S, N, 3), mass (S, N), drag (S, N), edge (S, N-1), bend (S, N-2),
//            torsion (S, N-3), integrity (S, N), angular (S, N-1), transition (), breaking (),
//            soft_ratio (), edge_rest_length (S, N-1), bend_rest_length (S, N-2),
//            torsion_rest_length (S, N-3), segment_length (S, N), num_pinned (S,) int64,
//            gravity (3,)]
//   poses:  [rotation0 (P0.., 3, 3), translation0 (P0.., 3), linear_velocity0 (P0.., 3),
//            rotation1, translation1, linear_velocity1], with P_j = 1 or the number of scenes
//   assemble_substep = -1: returns the new (x, v), each (..., S, N, 3);
//   assemble_substep = k >= 0: returns substep k's system assembled at the given (x, v):
//            blocks (..., S, N, 4, 3, 3) and rhs (..., S, N, 3) (the parity tests' debug mode).
//
//   frame_finish(<the arguments of frame>, Tensor[] finish_pose) -> (Tensor, Tensor, Tensor)
//   the frame (assemble_substep must be -1), then the frame's end of `finish` below on its
//   result, fused: returns x', v' (pinned particles at the head's rigid velocity) and the speed.
//
//   finish(Tensor x, Tensor v, Tensor num_pinned, Tensor[] pose) -> (Tensor, Tensor)
//   (finish.h; the Python op ams_torch::finish in ams_torch/sim/finish.py)
//   x, v: (..., S, N, 3); num_pinned (S,) int64; pose: [translation (P.., 3), linear_velocity,
//            angular_velocity], P = 1 or the number of scenes; returns v' (..., S, N, 3) and the
//            speed relative to the head (..., S, N).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/ArrayRef.h>

#include <optional>
#include <tuple>
#include <vector>

#include "frame/finish.h"
#include "frame/frame.h"

namespace ams_torch {
namespace frame {

// The op's schema, the same for both backends.
constexpr const char* kFrameSchema =
    "frame(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor[] poses" AMS_FRAME_SETTINGS_SCHEMA
    ", bool hermite, int assemble_substep) -> (Tensor, Tensor)";

constexpr const char* kFrameFinishSchema =
    "frame_finish(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor[] poses" AMS_FRAME_SETTINGS_SCHEMA
    ", bool hermite, int assemble_substep, Tensor[] finish_pose) "
    "-> (Tensor, Tensor, Tensor)";
constexpr const char* kFinishSchema =
    "finish(Tensor x, Tensor v, Tensor num_pinned, Tensor[] pose) -> (Tensor, Tensor)";

enum StateIndex { kX, kV, kGhostRest, kSagOffset, kStateCount };
enum ModelIndex {
  kRestPositions, kMass, kDrag, kEdge, kBend, kTorsion, kIntegrity, kAngular, kTransition, kBreaking, kSoftRatio,
  kEdgeLength, kBendLength, kTorsionLength, kSegmentLength, kNumPinned, kGravity, kModelCount
};
enum PoseIndex { kRotation0, kTranslation0, kVelocity0, kRotation1, kTranslation1, kVelocity1, kPoseCount };

// Validated, contiguous inputs of one call.
struct FrameInputs {
  std::vector<at::Tensor> state, model, poses;
  std::optional<at::Tensor> external_force;
  int64_t scenes = 0, strands = 0, particles = 0;
  int64_t pose_scenes[2] = {1, 1};
  FrameSettings settings{};
  int64_t assemble_substep = -1;
};

inline void check_shape(const char* op, const at::Tensor& t, const char* name, c10::IntArrayRef shape) {
  TORCH_CHECK(t.sizes() == shape, op, ": ", name, " must have shape ", shape, ", got ", t.sizes());
}

inline FrameInputs check_frame_inputs(const char* op, at::TensorList state, const std::optional<at::Tensor>& ext,
                                      at::TensorList model, at::TensorList poses AMS_FRAME_SETTINGS_PARAMS,
                                      bool hermite, int64_t assemble_substep) {
  TORCH_CHECK(state.size() == kStateCount, op, ": state must be [x, v, ghost_rest, sag_offset], got ", state.size(),
              " tensors");
  TORCH_CHECK(model.size() == kModelCount, op, ": model must hold ", int(kModelCount), " tensors, got ", model.size());
  TORCH_CHECK(poses.size() == kPoseCount, op, ": poses must hold ", int(kPoseCount), " tensors, got ", poses.size());
  const at::Tensor& x = state[kX];
  TORCH_CHECK(x.dim() >= 3 && x.size(-1) == 3, op, ": x must have shape (..., S, N, 3), got ", x.sizes());
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, op, ": float32 or float64 only, got ", dtype);
  FrameInputs in;
  in.strands = x.size(-3);
  in.particles = x.size(-2);
  const int64_t S = in.strands, N = in.particles;
  TORCH_CHECK(N >= 4, op, ": strands need at least 4 particles, got ", N);
  in.scenes = S > 0 ? x.numel() / (S * N * 3) : 0;
  TORCH_CHECK(substeps >= 1, op, ": substeps must be >= 1, got ", substeps);
  TORCH_CHECK(integrity_model >= 0 && integrity_model <= 2, op, ": integrity_model must be 0, 1 or 2");
  TORCH_CHECK(assemble_substep >= -1 && assemble_substep < substeps, op, ": assemble_substep must be in [-1, ",
              substeps, "), got ", assemble_substep);
  auto same = [&](const at::Tensor& t, const char* name, at::ScalarType want) {
    TORCH_CHECK(t.device() == x.device(), op, ": ", name, " is on ", t.device(), ", x on ", x.device());
    TORCH_CHECK(t.scalar_type() == want, op, ": ", name, " must be ", want, ", got ", t.scalar_type());
    return t.contiguous();
  };
  static const char* kStateNames[kStateCount] = {"x", "v", "ghost_rest", "sag_offset"};
  for (int i = 0; i < kStateCount; ++i) {
    check_shape(op, state[i], kStateNames[i], x.sizes());
    in.state.push_back(same(state[i], kStateNames[i], dtype));
  }
  if (ext.has_value()) {
    check_shape(op, *ext, "external_force", x.sizes());
    in.external_force = same(*ext, "external_force", dtype);
  }
  static const char* kModelNames[kModelCount] = {
      "rest_positions", "mass", "drag", "edge", "bend", "torsion", "integrity", "angular", "transition", "breaking",
      "soft_ratio", "edge_rest_length", "bend_rest_length", "torsion_rest_length", "segment_length", "num_pinned",
      "gravity"};
  const std::vector<std::vector<int64_t>> shapes = {
      {S, N, 3}, {S, N}, {S, N}, {S, N - 1}, {S, N - 2}, {S, N - 3}, {S, N}, {S, N - 1}, {}, {}, {},
      {S, N - 1}, {S, N - 2}, {S, N - 3}, {S, N}, {S}, {3}};
  for (int i = 0; i < kModelCount; ++i) {
    const bool scalar = i == kTransition || i == kBreaking || i == kSoftRatio;
    if (scalar) {
      TORCH_CHECK(model[i].numel() == 1, op, ": ", kModelNames[i], " must hold one value, got ", model[i].sizes());
    } else {
      check_shape(op, model[i], kModelNames[i], shapes[i]);
    }
    in.model.push_back(same(model[i], kModelNames[i], i == kNumPinned ? at::kLong : dtype));
  }
  static const char* kPoseNames[kPoseCount] = {"rotation0", "translation0", "linear_velocity0",
                                               "rotation1", "translation1", "linear_velocity1"};
  for (int j = 0; j < 2; ++j) {
    const at::Tensor& r = poses[3 * j];
    TORCH_CHECK(r.dim() >= 2 && r.size(-1) == 3 && r.size(-2) == 3, op, ": ", kPoseNames[3 * j],
                " must have shape (..., 3, 3), got ", r.sizes());
    const int64_t p = r.numel() / 9;
    TORCH_CHECK(p == 1 || p == in.scenes, op, ": ", kPoseNames[3 * j], " holds ", p, " poses for ", in.scenes,
                " scenes (give one, or one per scene)");
    in.pose_scenes[j] = p;
    for (int q = 0; q < 3; ++q) {
      const at::Tensor& t = poses[3 * j + q];
      TORCH_CHECK(t.numel() == (q == 0 ? 9 : 3) * p, op, ": ", kPoseNames[3 * j + q], " must hold ", p,
                  q == 0 ? " rotations" : " vectors", ", got shape ", t.sizes());
      in.poses.push_back(same(t, kPoseNames[3 * j + q], dtype));
    }
  }
  in.settings = FrameSettings{AMS_FRAME_SETTINGS_INIT hermite};
  in.assemble_substep = assemble_substep;
  return in;
}

template <class T>
FrameArgs<T> frame_args(const FrameInputs& in) {
  FrameArgs<T> a{};
  a.scenes = in.scenes;
  a.strands = in.strands;
  a.particles = in.particles;
  a.x = in.state[kX].const_data_ptr<T>();
  a.v = in.state[kV].const_data_ptr<T>();
  a.ghost_rest = in.state[kGhostRest].const_data_ptr<T>();
  a.sag_offset = in.state[kSagOffset].const_data_ptr<T>();
  a.external_force = in.external_force.has_value() ? in.external_force->const_data_ptr<T>() : nullptr;
  const auto& m = in.model;
  a.rest_positions = m[kRestPositions].const_data_ptr<T>();
  a.mass = m[kMass].const_data_ptr<T>();
  a.drag = m[kDrag].const_data_ptr<T>();
  a.stiffness[0] = m[kEdge].const_data_ptr<T>();
  a.stiffness[1] = m[kBend].const_data_ptr<T>();
  a.stiffness[2] = m[kTorsion].const_data_ptr<T>();
  a.rest_length[0] = m[kEdgeLength].const_data_ptr<T>();
  a.rest_length[1] = m[kBendLength].const_data_ptr<T>();
  a.rest_length[2] = m[kTorsionLength].const_data_ptr<T>();
  a.integrity = m[kIntegrity].const_data_ptr<T>();
  a.angular = m[kAngular].const_data_ptr<T>();
  a.segment_length = m[kSegmentLength].const_data_ptr<T>();
  a.num_pinned = m[kNumPinned].const_data_ptr<int64_t>();
  a.gravity = m[kGravity].const_data_ptr<T>();
  a.transition = m[kTransition].const_data_ptr<T>();
  a.breaking = m[kBreaking].const_data_ptr<T>();
  a.soft_ratio = m[kSoftRatio].const_data_ptr<T>();
  for (int j = 0; j < 2; ++j) {
    a.rotation[j] = in.poses[3 * j].const_data_ptr<T>();
    a.translation[j] = in.poses[3 * j + 1].const_data_ptr<T>();
    a.velocity[j] = in.poses[3 * j + 2].const_data_ptr<T>();
    a.pose_scenes[j] = in.pose_scenes[j];
  }
  return a;
}

// The two outputs: (x, v) like x, or (blocks (..., S, N, 4, 3, 3), rhs like x).
inline std::tuple<at::Tensor, at::Tensor> frame_outputs(const FrameInputs& in) {
  const at::Tensor& x = in.state[kX];
  const auto opts = x.options().memory_format(at::MemoryFormat::Contiguous);
  if (in.assemble_substep < 0) return {at::empty(x.sizes(), opts), at::empty(x.sizes(), opts)};
  std::vector<int64_t> shape(x.sizes().begin(), x.sizes().end() - 1);
  shape.insert(shape.end(), {banded::kBand + 1, 3, 3});
  return {at::empty(shape, opts), at::empty(x.sizes(), opts)};
}

// The finish pose [translation, linear_velocity, angular_velocity], each (P.., 3) with P = 1 or
// `scenes`, validated against x (device, dtype) and made contiguous.
inline void check_finish_pose(const char* op, at::TensorList pose, int64_t scenes, const at::Tensor& x,
                              at::Tensor* translation, at::Tensor* linear, at::Tensor* angular,
                              int64_t* pose_scenes) {
  TORCH_CHECK(pose.size() == 3, op, ": pose must be [translation, linear_velocity, angular_velocity], got ",
              pose.size(), " tensors");
  static const char* kNames[3] = {"translation", "linear_velocity", "angular_velocity"};
  const int64_t p = pose[0].numel() / 3;
  TORCH_CHECK(p == 1 || p == scenes, op, ": translation holds ", p, " poses for ", scenes,
              " scenes (give one, or one per scene)");
  *pose_scenes = p;
  at::Tensor* dst[3] = {translation, linear, angular};
  for (int q = 0; q < 3; ++q) {
    TORCH_CHECK(pose[q].numel() == 3 * p && pose[q].dim() >= 1 && pose[q].size(-1) == 3, op, ": ", kNames[q],
                " must hold ", p, " vectors, got shape ", pose[q].sizes());
    TORCH_CHECK(pose[q].device() == x.device(), op, ": ", kNames[q], " is on ", pose[q].device(), ", x on ",
                x.device());
    TORCH_CHECK(pose[q].scalar_type() == x.scalar_type(), op, ": ", kNames[q], " must be ", x.scalar_type(),
                ", got ", pose[q].scalar_type());
    *dst[q] = pose[q].contiguous();
  }
}

// Validated, contiguous inputs of one finish call and its outputs (v', speed).
struct FinishInputs {
  at::Tensor x, v, num_pinned, translation, linear, angular, v_out, speed;
  int64_t scenes = 0, strands = 0, particles = 0, pose_scenes = 1;
};

inline FinishInputs check_finish_inputs(const char* op, const at::Tensor& x, const at::Tensor& v,
                                        const at::Tensor& num_pinned, at::TensorList pose) {
  TORCH_CHECK(x.dim() >= 3 && x.size(-1) == 3, op, ": x must have shape (..., S, N, 3), got ", x.sizes());
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, op, ": float32 or float64 only, got ", dtype);
  check_shape(op, v, "v", x.sizes());
  FinishInputs in;
  in.strands = x.size(-3);
  in.particles = x.size(-2);
  in.scenes = in.strands * in.particles > 0 ? x.numel() / (in.strands * in.particles * 3) : 0;
  check_shape(op, num_pinned, "num_pinned", {in.strands});
  auto same = [&](const at::Tensor& t, const char* name, at::ScalarType want) {
    TORCH_CHECK(t.device() == x.device(), op, ": ", name, " is on ", t.device(), ", x on ", x.device());
    TORCH_CHECK(t.scalar_type() == want, op, ": ", name, " must be ", want, ", got ", t.scalar_type());
    return t.contiguous();
  };
  in.x = same(x, "x", dtype);
  in.v = same(v, "v", dtype);
  in.num_pinned = same(num_pinned, "num_pinned", at::kLong);
  check_finish_pose(op, pose, in.scenes, x, &in.translation, &in.linear, &in.angular, &in.pose_scenes);
  const auto opts = x.options().memory_format(at::MemoryFormat::Contiguous);
  in.v_out = at::empty(x.sizes(), opts);
  in.speed = at::empty(x.sizes().slice(0, x.dim() - 1), opts);
  return in;
}

// The frame's end fused into a frame (frame_finish): on the frame's outputs x', v', v' updated in
// place (each particle's v is read before it is written), speed allocated here.
inline FinishInputs fused_finish_inputs(const char* op, const FrameInputs& in, const at::Tensor& x,
                                        const at::Tensor& v, at::TensorList pose) {
  TORCH_CHECK(in.assemble_substep < 0, op, ": the frame's end needs a whole frame (assemble_substep = -1)");
  FinishInputs f;
  f.scenes = in.scenes;
  f.strands = in.strands;
  f.particles = in.particles;
  f.x = x;
  f.v = v;
  f.v_out = v;
  f.num_pinned = in.model[kNumPinned];
  check_finish_pose(op, pose, in.scenes, x, &f.translation, &f.linear, &f.angular, &f.pose_scenes);
  f.speed = at::empty(x.sizes().slice(0, x.dim() - 1), x.options().memory_format(at::MemoryFormat::Contiguous));
  return f;
}

template <class T>
FinishArgs<T> finish_args(const FinishInputs& in) {
  return FinishArgs<T>{in.scenes,
                       in.strands,
                       in.particles,
                       in.pose_scenes,
                       in.x.const_data_ptr<T>(),
                       in.v.const_data_ptr<T>(),
                       in.translation.const_data_ptr<T>(),
                       in.linear.const_data_ptr<T>(),
                       in.angular.const_data_ptr<T>(),
                       in.num_pinned.const_data_ptr<int64_t>(),
                       in.v_out.mutable_data_ptr<T>(),
                       in.speed.mutable_data_ptr<T>()};
}

} // namespace frame
} // namespace ams_torch
