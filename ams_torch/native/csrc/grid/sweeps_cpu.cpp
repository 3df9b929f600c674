// CPU kernels of the pressure sweeps and their adjoint: ops `ams_torch_cpu::sweeps` and
// `sweeps_adjoint` (schemas in sweeps_binding.h, arithmetic in sweeps.h). A sweep's slots in
// parallel (at::parallel_for; each slot reads the previous φ, writes its own); the adjoint keeps φ
// before each sweep (iterations × (L + 1) values), then runs the sweeps in reverse: the per-slot
// part in parallel, the scatter of φ̄ into the neighbours gathered by destination (each slot's
// incoming entries in index_add's order, direction-major), in parallel, so the sums are the torch
// definition's.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <tuple>
#include <vector>

#include "grid/sweeps.h"
#include "grid/sweeps_binding.h"
#include "grid/sweeps_cpu.h"

namespace ams_torch {
namespace grid {
namespace {

template <class T>
void run_sweeps(const SweepsInputs& in, int64_t iterations, T keep, T* history, T* out) {
  host_sweeps::forward<T>(in.src.const_data_ptr<T>(), in.coef.const_data_ptr<T>(), in.w.const_data_ptr<T>(),
                         in.nbr.const_data_ptr<int64_t>(), in.slots, iterations, keep, history, out);
}

template <class T>
void run_adjoint(const SweepsInputs& in, int64_t iterations, T keep, T* g_src, T* g_coef, T* g_w) {
  const int64_t n1 = in.slots;
  std::vector<T> history(static_cast<size_t>(iterations * n1));
  std::vector<T> last(static_cast<size_t>(n1));
  run_sweeps<T>(in, iterations, keep, history.data(), last.data());
  host_sweeps::reverse<T>(in.src.const_data_ptr<T>(), in.coef.const_data_ptr<T>(), in.w.const_data_ptr<T>(),
                         in.nbr.const_data_ptr<int64_t>(), n1, iterations, keep, history.data(),
                         in.g.const_data_ptr<T>(), g_src, g_coef, g_w);
}

at::Tensor sweeps_cpu(const at::Tensor& src, const at::Tensor& coef, const at::Tensor& w, const at::Tensor& nbr,
                      int64_t iterations, double omega) {
  constexpr const char* op = "ams_torch_cpu::sweeps";
  const SweepsInputs in = check_sweeps_inputs(op, src, coef, w, nbr, iterations, nullptr);
  TORCH_CHECK(in.src.device().is_cpu(), op, ": CPU tensors expected");
  at::Tensor out = at::empty({in.slots}, in.src.options());
  AT_DISPATCH_FLOATING_TYPES(in.src.scalar_type(), op, [&] {
    run_sweeps<scalar_t>(in, iterations, scalar_t(1.0 - omega), nullptr, out.mutable_data_ptr<scalar_t>());
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sweeps_adjoint_cpu(const at::Tensor& src, const at::Tensor& coef,
                                                                  const at::Tensor& w, const at::Tensor& nbr,
                                                                  int64_t iterations, double omega,
                                                                  const at::Tensor& g) {
  constexpr const char* op = "ams_torch_cpu::sweeps_adjoint";
  const SweepsInputs in = check_sweeps_inputs(op, src, coef, w, nbr, iterations, &g);
  TORCH_CHECK(in.src.device().is_cpu(), op, ": CPU tensors expected");
  at::Tensor g_src = at::zeros({in.slots}, in.src.options()), g_coef = at::zeros({in.slots}, in.src.options());
  at::Tensor g_w = at::zeros({kSweepDirs, in.slots}, in.src.options());
  AT_DISPATCH_FLOATING_TYPES(in.src.scalar_type(), op, [&] {
    run_adjoint<scalar_t>(in, iterations, scalar_t(1.0 - omega), g_src.mutable_data_ptr<scalar_t>(),
                          g_coef.mutable_data_ptr<scalar_t>(), g_w.mutable_data_ptr<scalar_t>());
  });
  return {g_src, g_coef, g_w.reshape(w.sizes())};
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::grid::kSweepsSchema);
  m.def(ams_torch::grid::kSweepsAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("sweeps", &ams_torch::grid::sweeps_cpu);
  m.impl("sweeps_adjoint", &ams_torch::grid::sweeps_adjoint_cpu);
}
