// Torch side of the fused collision stage, shared by the CPU kernel (collide_cpu.cpp) and the
// CUDA binding (collide_cuda_binding.cpp): validation and the raw-pointer CollideArgs of
// collide.h. Never included by CUDA sources (it needs torch headers).
//
// Op schema (both backends; the Python op ams_torch::collisions in ams_torch/sim/native.py
// documents shapes and units):
//   collide(Tensor x, Tensor v, Tensor[] model, Tensor head_rotation, Tensor[] collider_tensors,
//           Tensor[] collider_poses, int[] collider_ints, float[] collider_floats, float dt,
//           int rounds, bool inextensibility, float ftl_damping) -> (Tensor, Tensor)
//   x, v: (..., S, N, 3); model: [rest_positions (S, N, 3), edge_rest_length (S, N-1),
//   num_pinned (S,) int64]; head_rotation (P.., 3, 3) with P = 1 or the number of scenes;
//   per collider c (C of them, C <= kMaxColliders):
//     collider_tensors[4c .. 4c+3] = friction (), g0, g1, g2 (collide.h: ColliderArgs);
//     collider_poses[4c .. 4c+3] = R (P.., 3, 3), t (P.., 3), linear and angular velocity (P.., 3);
//     collider_ints[3c .. 3c+2] = type, projection iterations, has velocity;
//     collider_floats[3c .. 3c+2] = the shape's numbers.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/ArrayRef.h>

#include <tuple>
#include <vector>

#include "collide/collide.h"

namespace ams_torch {
namespace collide {

constexpr const char* kCollideSchema =
    "collide(Tensor x, Tensor v, Tensor[] model, Tensor head_rotation, Tensor[] collider_tensors, "
    "Tensor[] collider_poses, int[] collider_ints, float[] collider_floats, float dt, int rounds, "
    "bool inextensibility, float ftl_damping) -> (Tensor, Tensor)";

// The adjoint (collide_adjoint.h): the same inputs and the adjoints x_bar, v_bar of the outputs;
// returns x̄, v̄ (..., S, N, 3), the colliders' pose and friction adjoints (B, S, C, 19: R̄ row-major,
// t̄, linear, angular, μ̄; each strand's share) and the head rotation's (B, S, 9).
constexpr const char* kCollideAdjointSchema =
    "collide_adjoint(Tensor x, Tensor v, Tensor[] model, Tensor head_rotation, Tensor[] collider_tensors, "
    "Tensor[] collider_poses, int[] collider_ints, float[] collider_floats, float dt, int rounds, "
    "bool inextensibility, float ftl_damping, Tensor x_bar, Tensor v_bar) -> (Tensor, Tensor, Tensor, Tensor)";

struct CollideInputs {
  at::Tensor x, v, rest, edge, num_pinned, head;
  std::vector<at::Tensor> tensors, poses; // contiguous, kept alive
  std::vector<int64_t> ints;
  std::vector<double> floats;
  int64_t scenes = 0, strands = 0, particles = 0, head_scenes = 1, count = 0;
  std::vector<int64_t> pose_scenes;
  CollideSettings settings{};
};

inline CollideInputs check_collide_inputs(const char* op, const at::Tensor& x, const at::Tensor& v,
                                          at::TensorList model, const at::Tensor& head, at::TensorList tensors,
                                          at::TensorList poses, c10::IntArrayRef ints, c10::ArrayRef<double> floats,
                                          double dt, int64_t rounds, bool inextensibility, double ftl_damping) {
  TORCH_CHECK(x.dim() >= 3 && x.size(-1) == 3, op, ": x must have shape (..., S, N, 3), got ", x.sizes());
  TORCH_CHECK(v.sizes() == x.sizes(), op, ": v must have shape ", x.sizes(), ", got ", v.sizes());
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, op, ": float32 or float64 only, got ", dtype);
  TORCH_CHECK(model.size() == 3, op, ": model must be [rest_positions, edge_rest_length, num_pinned]");
  CollideInputs in;
  in.strands = x.size(-3);
  in.particles = x.size(-2);
  const int64_t S = in.strands, N = in.particles;
  TORCH_CHECK(N >= 2, op, ": strands need at least 2 particles, got ", N);
  in.scenes = S > 0 ? x.numel() / (S * N * 3) : 0;
  auto same = [&](const at::Tensor& t, const char* name, at::ScalarType want) {
    TORCH_CHECK(t.device() == x.device(), op, ": ", name, " is on ", t.device(), ", x on ", x.device());
    TORCH_CHECK(t.scalar_type() == want, op, ": ", name, " must be ", want, ", got ", t.scalar_type());
    return t.contiguous();
  };
  auto scenes_of = [&](const at::Tensor& t, int64_t per, const char* name) {
    TORCH_CHECK(t.numel() % per == 0 && t.numel() > 0, op, ": ", name, " has shape ", t.sizes());
    const int64_t p = t.numel() / per;
    TORCH_CHECK(p == 1 || p == in.scenes, op, ": ", name, " holds ", p, " entries for ", in.scenes, " scenes");
    return p;
  };
  in.x = same(x, "x", dtype);
  in.v = same(v, "v", dtype);
  TORCH_CHECK(model[0].sizes() == c10::IntArrayRef({S, N, 3}), op, ": rest_positions must be (S, N, 3)");
  TORCH_CHECK(model[1].sizes() == c10::IntArrayRef({S, N - 1}), op, ": edge_rest_length must be (S, N - 1)");
  TORCH_CHECK(model[2].sizes() == c10::IntArrayRef({S}), op, ": num_pinned must be (S,)");
  in.rest = same(model[0], "rest_positions", dtype);
  in.edge = same(model[1], "edge_rest_length", dtype);
  in.num_pinned = same(model[2], "num_pinned", at::kLong);
  in.head = same(head, "head_rotation", dtype);
  in.head_scenes = scenes_of(in.head, 9, "head_rotation");
  in.count = int64_t(ints.size()) / 3;
  TORCH_CHECK(int64_t(ints.size()) == 3 * in.count && int64_t(floats.size()) == 3 * in.count &&
                  int64_t(tensors.size()) == 4 * in.count && int64_t(poses.size()) == 4 * in.count,
              op, ": per collider: 4 tensors, 4 pose tensors, 3 ints and 3 floats");
  TORCH_CHECK(in.count <= kMaxColliders, op, ": at most ", kMaxColliders, " colliders, got ", in.count);
  in.ints.assign(ints.begin(), ints.end());
  in.floats.assign(floats.begin(), floats.end());
  for (int64_t c = 0; c < in.count; ++c) {
    const int64_t type = ints[3 * c];
    TORCH_CHECK(type >= 0 && type < kColliderTypes, op, ": collider ", c, " has unknown type ", type);
    in.tensors.push_back(same(tensors[4 * c], "friction", dtype));
    TORCH_CHECK(in.tensors.back().numel() == 1, op, ": collider ", c, ": friction must hold one value");
    const int64_t need[kColliderTypes][3] = {{3, 0, 0}, {3, 3, 0}, {3, 3, 0}, {3, 9, 0}, {-1, 3, 3}};
    for (int g = 0; g < 3; ++g) {
      const at::Tensor t = same(tensors[4 * c + 1 + g], "collider geometry", dtype);
      const int64_t want = need[type][g];
      if (want > 0) {
        TORCH_CHECK(t.numel() == want, op, ": collider ", c, " geometry tensor ", g, " must hold ", want,
                    " values, got ", t.sizes());
      } else if (want < 0) {
        TORCH_CHECK(t.dim() == 4 && t.size(3) == 4 && t.size(0) >= 2 && t.size(1) >= 2 && t.size(2) >= 2, op,
                    ": collider ", c, " volume must be (nz, ny, nx, 4) (channels last), got ", t.sizes());
      }
      in.tensors.push_back(t);
    }
    const int64_t p = scenes_of(poses[4 * c], 9, "collider rotation");
    in.pose_scenes.push_back(p);
    for (int q = 0; q < 4; ++q) {
      const at::Tensor t = same(poses[4 * c + q], "collider pose", dtype);
      TORCH_CHECK(t.numel() == (q == 0 ? 9 : 3) * p, op, ": collider ", c, " pose tensor ", q, " has shape ",
                  t.sizes());
      in.poses.push_back(t);
    }
  }
  TORCH_CHECK(rounds >= 0, op, ": rounds must be >= 0");
  in.settings = CollideSettings{dt, int(rounds), inextensibility, ftl_damping};
  return in;
}

// The adjoint's own conditions (besides check_collide_inputs): no hollow sphere, at most
// kMaxPushout push-out passes, output adjoints of x's shape; returns them contiguous.
inline std::tuple<at::Tensor, at::Tensor> check_adjoint_inputs(const char* op, const CollideInputs& in,
                                                              const at::Tensor& x_bar, const at::Tensor& v_bar,
                                                              int max_pushout) {
  for (int64_t c = 0; c < in.count; ++c) {
    TORCH_CHECK(in.ints[3 * c] != kHollowSphere, op, ": collider ", c, " is a hollow sphere, which has no native adjoint");
    TORCH_CHECK(in.ints[3 * c + 1] <= max_pushout, op, ": collider ", c, " has ", in.ints[3 * c + 1],
                " push-out passes; the native adjoint keeps at most ", max_pushout);
  }
  for (const at::Tensor* t : {&x_bar, &v_bar}) {
    TORCH_CHECK(t->sizes() == in.x.sizes(), op, ": the output adjoints must have shape ", in.x.sizes(), ", got ",
                t->sizes());
    TORCH_CHECK(t->scalar_type() == in.x.scalar_type() && t->device() == in.x.device(), op,
                ": the output adjoints must have x's dtype and device");
  }
  return {x_bar.contiguous(), v_bar.contiguous()};
}

template <class T>
CollideArgs<T> collide_args(const CollideInputs& in) {
  CollideArgs<T> a{};
  a.scenes = in.scenes;
  a.strands = in.strands;
  a.particles = in.particles;
  a.x = in.x.const_data_ptr<T>();
  a.v = in.v.const_data_ptr<T>();
  a.rest_positions = in.rest.const_data_ptr<T>();
  a.edge_rest_length = in.edge.const_data_ptr<T>();
  a.num_pinned = in.num_pinned.const_data_ptr<int64_t>();
  a.head_rotation = in.head.const_data_ptr<T>();
  a.head_scenes = in.head_scenes;
  a.count = int(in.count);
  for (int64_t c = 0; c < in.count; ++c) {
    ColliderArgs<T>& k = a.colliders[c];
    k.type = int(in.ints[3 * c]);
    k.iterations = int(in.ints[3 * c + 1]);
    k.has_velocity = int(in.ints[3 * c + 2] != 0);
    k.pose_scenes = in.pose_scenes[c];
    k.friction = in.tensors[4 * c].const_data_ptr<T>();
    k.g0 = in.tensors[4 * c + 1].const_data_ptr<T>();
    k.g1 = in.tensors[4 * c + 2].const_data_ptr<T>();
    k.g2 = in.tensors[4 * c + 3].const_data_ptr<T>();
    for (int q = 0; q < 3; ++q) k.f[q] = in.floats[3 * c + q];
    if (k.type == kMesh) {
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

} // namespace collide
} // namespace ams_torch
