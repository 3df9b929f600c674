// Torch side of the fused frame with substep contact (Params(contact="substep")), shared by the
// CPU kernel (frame_cpu.cpp) and the CUDA binding (frame_cuda_binding.cpp): validation of the
// colliders and the raw-pointer ContactArgs of frame.h. Never included by CUDA sources.
//
// Op schema (both backends; the Python op ams_torch::frame_contact in
// ams_torch/sim/native_contact.py documents shapes and units):
//   frame_contact(<the arguments of frame, assemble_substep excluded>, Tensor[] collider_tensors,
//                 Tensor[] collider_poses, int[] collider_ints, float[] collider_floats)
//       -> (Tensor, Tensor)
//   per collider c (C of them, C <= collide::kMaxColliders), as the collision op
//   (collide_binding.h) but with one world pose per substep:
//     collider_tensors[4c .. 4c+3] = friction (), g0, g1, g2;
//     collider_poses[4c .. 4c+3] = R (M, P.., 3, 3), t (M, P.., 3), linear and angular velocity
//                                  (M, P.., 3), P = 1 or the number of scenes;
//     collider_ints[3c .. 3c+2] = type, projection iterations, has velocity;
//     collider_floats[3c .. 3c+2] = the shape's numbers.
//   Returns the new (x, v), each (..., S, N, 3).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/ArrayRef.h>

#include <vector>

#include "collide/collide.h"
#include "frame/frame.h"
#include "frame/frame_binding.h"

namespace ams_torch {
namespace frame {

constexpr const char* kFrameContactSchema =
    "frame_contact(Tensor[] state, Tensor? external_force, Tensor[] model, Tensor[] poses" AMS_FRAME_SETTINGS_SCHEMA
    ", bool hermite, Tensor[] collider_tensors, "
    "Tensor[] collider_poses, int[] collider_ints, float[] collider_floats) -> (Tensor, Tensor)";

// Validated, contiguous colliders of one call (kept alive with the tensors).
struct ContactInputs {
  std::vector<at::Tensor> tensors, poses;
  std::vector<int64_t> ints, pose_scenes;
  std::vector<double> floats;
  int64_t count = 0;
};

inline ContactInputs check_contact_inputs(const char* op, const FrameInputs& in, at::TensorList tensors,
                                          at::TensorList poses, c10::IntArrayRef ints, c10::ArrayRef<double> floats) {
  const at::Tensor& x = in.state[kX];
  const int64_t M = in.settings.substeps;
  ContactInputs c;
  c.count = int64_t(ints.size()) / 3;
  TORCH_CHECK(int64_t(ints.size()) == 3 * c.count && int64_t(floats.size()) == 3 * c.count &&
                  int64_t(tensors.size()) == 4 * c.count && int64_t(poses.size()) == 4 * c.count,
              op, ": per collider: 4 tensors, 4 pose tensors, 3 ints and 3 floats");
  TORCH_CHECK(c.count >= 1 && c.count <= collide::kMaxColliders, op, ": 1 to ", collide::kMaxColliders,
              " colliders, got ", c.count);
  TORCH_CHECK(in.assemble_substep < 0, op, ": substep contact runs whole frames");
  auto same = [&](const at::Tensor& t, const char* name) {
    TORCH_CHECK(t.device() == x.device(), op, ": ", name, " is on ", t.device(), ", x on ", x.device());
    TORCH_CHECK(t.scalar_type() == x.scalar_type(), op, ": ", name, " must be ", x.scalar_type(), ", got ",
                t.scalar_type());
    return t.contiguous();
  };
  c.ints.assign(ints.begin(), ints.end());
  c.floats.assign(floats.begin(), floats.end());
  for (int64_t k = 0; k < c.count; ++k) {
    const int64_t type = ints[3 * k];
    TORCH_CHECK(type >= 0 && type < collide::kColliderTypes, op, ": collider ", k, " has unknown type ", type);
    c.tensors.push_back(same(tensors[4 * k], "friction"));
    TORCH_CHECK(c.tensors.back().numel() == 1, op, ": collider ", k, ": friction must hold one value");
    const int64_t need[collide::kColliderTypes][3] = {{3, 0, 0}, {3, 3, 0}, {3, 3, 0}, {3, 9, 0}, {-1, 3, 3}};
    for (int g = 0; g < 3; ++g) {
      const at::Tensor t = same(tensors[4 * k + 1 + g], "collider geometry");
      const int64_t want = need[type][g];
      if (want > 0) {
        TORCH_CHECK(t.numel() == want, op, ": collider ", k, " geometry tensor ", g, " must hold ", want,
                    " values, got ", t.sizes());
      } else if (want < 0) {
        TORCH_CHECK(t.dim() == 4 && t.size(3) == 4 && t.size(0) >= 2 && t.size(1) >= 2 && t.size(2) >= 2, op,
                    ": collider ", k, " volume must be (nz, ny, nx, 4) (channels last), got ", t.sizes());
      }
      c.tensors.push_back(t);
    }
    const at::Tensor& r = poses[4 * k];
    TORCH_CHECK(r.numel() % (9 * M) == 0 && r.numel() > 0, op, ": collider ", k, " rotations must be (M, P.., 3, 3)",
                " for M = ", M, " substeps, got ", r.sizes());
    const int64_t p = r.numel() / (9 * M);
    TORCH_CHECK(p == 1 || p == in.scenes, op, ": collider ", k, " holds ", p, " poses per substep for ", in.scenes,
                " scenes");
    c.pose_scenes.push_back(p);
    for (int q = 0; q < 4; ++q) {
      const at::Tensor t = same(poses[4 * k + q], "collider pose");
      TORCH_CHECK(t.numel() == (q == 0 ? 9 : 3) * p * M, op, ": collider ", k, " pose tensor ", q, " has shape ",
                  t.sizes());
      c.poses.push_back(t);
    }
  }
  return c;
}

template <class T>
ContactArgs<T> contact_args(const ContactInputs& in) {
  ContactArgs<T> a{};
  a.count = int(in.count);
  for (int64_t c = 0; c < in.count; ++c) {
    collide::ColliderArgs<T>& k = a.colliders[c];
    k.type = int(in.ints[3 * c]);
    k.iterations = int(in.ints[3 * c + 1]);
    k.has_velocity = int(in.ints[3 * c + 2] != 0);
    k.pose_scenes = in.pose_scenes[c];
    k.friction = in.tensors[4 * c].const_data_ptr<T>();
    k.g0 = in.tensors[4 * c + 1].const_data_ptr<T>();
    k.g1 = in.tensors[4 * c + 2].const_data_ptr<T>();
    k.g2 = in.tensors[4 * c + 3].const_data_ptr<T>();
    for (int q = 0; q < 3; ++q) k.f[q] = in.floats[3 * c + q];
    if (k.type == collide::kMesh) {
      const at::Tensor& vol = in.tensors[4 * c + 1];
      k.nz = vol.size(0);
      k.ny = vol.size(1);
      k.nx = vol.size(2);
    }
    k.rotation = in.poses[4 * c].const_data_ptr<T>();
    k.translation = in.poses[4 * c + 1].const_data_ptr<T>();
    k.linear_velocity = in.poses[4 * c + 2].const_data_ptr<T>();
    k.angular_velocity = in.poses[4 * c + 3].const_data_ptr<T>();
  }
  return a;
}

} // namespace frame
} // namespace ams_torch
