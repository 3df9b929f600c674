// Torch side of the finish and yield adjoints, shared by the CPU kernel (finish_adjoint_cpu.cpp) and
// the CUDA binding (finish_adjoint_cuda_binding.cpp): schemas and validation. Never included by CUDA
// sources.
//
//   finish_adjoint(Tensor x, Tensor v, Tensor num_pinned, Tensor[] pose, Tensor g_v, Tensor? g_speed)
//       -> (Tensor g_x, Tensor g_v, Tensor g_pose)
//     x, v, g_v (..., S, N, 3); num_pinned (S,) int64; pose [t, lin, ang] as the finish op's; g_speed
//     (..., S, N) or None; g_pose (B S, 9): each strand's adjoints of t, lin, ang (summed by the caller).
//   yield_adjoint(Tensor x_local, Tensor anchor, Tensor limit, Tensor free, Tensor g_new)
//       -> (Tensor g_x, Tensor g_anchor, Tensor g_limit)
//     x_local, anchor, g_new (..., S, N, 3) m, head frame; limit (S, N) m; free (S, N) bool; g_limit
//     (..., S, N).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <optional>

#include "frame/frame_binding.h"

namespace ams_torch {
namespace frame {

constexpr const char* kFinishAdjointSchema =
    "finish_adjoint(Tensor x, Tensor v, Tensor num_pinned, Tensor[] pose, Tensor g_v, Tensor? g_speed) -> "
    "(Tensor, Tensor, Tensor)";
constexpr const char* kYieldAdjointSchema =
    "yield_adjoint(Tensor x_local, Tensor anchor, Tensor limit, Tensor free, Tensor g_new) -> (Tensor, Tensor, Tensor)";

struct FinishAdjointInputs {
  FinishInputs in;
  at::Tensor g_v, g_speed; // g_speed undefined: none
};

inline FinishAdjointInputs check_finish_adjoint_inputs(const char* op, const at::Tensor& x, const at::Tensor& v,
                                                       const at::Tensor& num_pinned, at::TensorList pose,
                                                       const at::Tensor& g_v,
                                                       const std::optional<at::Tensor>& g_speed) {
  FinishAdjointInputs out{check_finish_inputs(op, x, v, num_pinned, pose), at::Tensor(), at::Tensor()};
  TORCH_CHECK(g_v.sizes() == x.sizes() && g_v.scalar_type() == x.scalar_type() && g_v.device() == x.device(), op,
              ": g_v must be like x ", x.sizes(), ", got ", g_v.sizes());
  out.g_v = g_v.contiguous();
  if (g_speed.has_value() && g_speed->defined()) {
    TORCH_CHECK(g_speed->sizes() == x.sizes().slice(0, x.dim() - 1) && g_speed->scalar_type() == x.scalar_type() &&
                    g_speed->device() == x.device(),
                op, ": g_speed must be (..., S, N) like x, got ", g_speed->sizes());
    out.g_speed = g_speed->contiguous();
  }
  return out;
}

struct YieldInputs {
  at::Tensor x, anchor, limit, free, g_new;
  int64_t count = 0, strands = 0, particles = 0; // count: particles in all (B S N)
};

inline YieldInputs check_yield_inputs(const char* op, const at::Tensor& x, const at::Tensor& anchor,
                                      const at::Tensor& limit, const at::Tensor& free, const at::Tensor& g_new) {
  TORCH_CHECK(x.dim() >= 3 && x.size(-1) == 3, op, ": x_local must have shape (..., S, N, 3), got ", x.sizes());
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, op, ": float32 or float64 only, got ", dtype);
  YieldInputs in;
  in.strands = x.size(-3);
  in.particles = x.size(-2);
  in.count = x.numel() / 3;
  for (const auto& [t, name] : {std::pair<const at::Tensor&, const char*>{anchor, "anchor"}, {g_new, "g_new"}})
    TORCH_CHECK(t.sizes() == x.sizes() && t.scalar_type() == dtype && t.device() == x.device(), op, ": ", name,
                " must be like x_local ", x.sizes(), ", got ", t.sizes(), " ", t.scalar_type());
  TORCH_CHECK(limit.sizes() == at::IntArrayRef({in.strands, in.particles}) && limit.scalar_type() == dtype &&
                  limit.device() == x.device(),
              op, ": limit must be (S, N) of ", dtype, ", got ", limit.sizes());
  TORCH_CHECK(free.sizes() == at::IntArrayRef({in.strands, in.particles}) && free.scalar_type() == at::kBool &&
                  free.device() == x.device(),
              op, ": free must be a bool tensor (S, N), got ", free.sizes(), " ", free.scalar_type());
  in.x = x.contiguous();
  in.anchor = anchor.contiguous();
  in.limit = limit.contiguous();
  in.free = free.contiguous();
  in.g_new = g_new.contiguous();
  return in;
}

} // namespace frame
} // namespace ams_torch
