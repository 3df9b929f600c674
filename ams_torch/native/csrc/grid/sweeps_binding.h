// Torch side of the pressure sweeps and their adjoint, shared by the CPU kernel (sweeps_cpu.cpp) and
// the CUDA binding (sweeps_cuda_binding.cpp): schemas and validation. Never included by CUDA sources.
//
//   sweeps(Tensor src, Tensor coef, Tensor w, Tensor nbr, int iterations, float omega) -> Tensor
//   sweeps_adjoint(Tensor src, Tensor coef, Tensor w, Tensor nbr, int iterations, float omega,
//                  Tensor g) -> (Tensor, Tensor, Tensor)
// src, coef, g: (L + 1,); w: (6, L + 1); nbr: (6 (L + 1),) or (6, L + 1) int64 list slots in [0, L];
// returns φ (L + 1,) after `iterations` sweeps from 0, or the adjoints of src, coef, w (sweeps.h).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include "grid/sweeps.h"

namespace ams_torch {
namespace grid {

constexpr const char* kSweepsSchema =
    "sweeps(Tensor src, Tensor coef, Tensor w, Tensor nbr, int iterations, float omega) -> Tensor";
constexpr const char* kSweepsAdjointSchema =
    "sweeps_adjoint(Tensor src, Tensor coef, Tensor w, Tensor nbr, int iterations, float omega, Tensor g) -> "
    "(Tensor, Tensor, Tensor)";

struct SweepsInputs {
  at::Tensor src, coef, w, nbr, g;
  int64_t slots = 0; // L + 1
};

inline SweepsInputs check_sweeps_inputs(const char* op, const at::Tensor& src, const at::Tensor& coef,
                                        const at::Tensor& w, const at::Tensor& nbr, int64_t iterations,
                                        const at::Tensor* g) {
  TORCH_CHECK(src.dim() == 1 && src.numel() >= 1, op, ": src must be (L + 1,), got ", src.sizes());
  const int64_t n1 = src.numel();
  const auto dtype = src.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, op, ": float32 or float64 only, got ", dtype);
  TORCH_CHECK(coef.sizes() == src.sizes() && coef.scalar_type() == dtype, op, ": coef must be like src");
  TORCH_CHECK(w.numel() == kSweepDirs * n1 && w.scalar_type() == dtype, op, ": w must be (6, ", n1, ") of ", dtype,
              ", got ", w.sizes());
  TORCH_CHECK(nbr.numel() == kSweepDirs * n1 && nbr.scalar_type() == at::kLong, op, ": nbr must be 6 x ", n1,
              " int64, got ", nbr.sizes(), " ", nbr.scalar_type());
  TORCH_CHECK(iterations >= 0, op, ": iterations must be >= 0");
  for (const at::Tensor* t : {&coef, &w, &nbr})
    TORCH_CHECK(t->device() == src.device(), op, ": every input on ", src.device());
  SweepsInputs in{src.contiguous(), coef.contiguous(), w.contiguous(), nbr.contiguous(), at::Tensor(), n1};
  if (g != nullptr) {
    TORCH_CHECK(g->sizes() == src.sizes() && g->scalar_type() == dtype && g->device() == src.device(), op,
                ": g must be like src");
    in.g = g->contiguous();
  }
  return in;
}

} // namespace grid
} // namespace ams_torch
