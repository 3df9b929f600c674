// Torch binding of the CUDA pressure sweeps and their adjoint: ops `ams_torch_cuda::sweeps` and
// `sweeps_adjoint` (schemas in sweeps_binding.h). Built only against a CUDA torch; the kernels are in
// sweeps_cuda.cu. Current CUDA stream of the inputs' device, workspace from torch's caching
// allocator, no host synchronisation.
#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <tuple>

#include "grid/sweeps_binding.h"
#include "grid/sweeps_cuda.h"

namespace ams_torch {
namespace grid {

at::Tensor sweeps_cuda_op(const at::Tensor& src, const at::Tensor& coef, const at::Tensor& w, const at::Tensor& nbr,
                          int64_t iterations, double omega) {
  constexpr const char* op = "ams_torch_cuda::sweeps";
  const SweepsInputs in = check_sweeps_inputs(op, src, coef, w, nbr, iterations, nullptr);
  TORCH_CHECK(in.src.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(in.src.device());
  at::Tensor out = at::empty({in.slots}, in.src.options());
  at::Tensor ws = at::empty({sweeps_cuda_workspace_elems(in.slots, iterations, false)}, in.src.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(in.src.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.src.scalar_type(), op, [&] {
    err = sweeps_cuda<scalar_t>(in.src.const_data_ptr<scalar_t>(), in.coef.const_data_ptr<scalar_t>(),
                                in.w.const_data_ptr<scalar_t>(), in.nbr.const_data_ptr<int64_t>(), in.slots, iterations,
                                scalar_t(1.0 - omega), out.mutable_data_ptr<scalar_t>(),
                                ws.mutable_data_ptr<scalar_t>(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sweeps_adjoint_cuda_op(const at::Tensor& src, const at::Tensor& coef,
                                                                      const at::Tensor& w, const at::Tensor& nbr,
                                                                      int64_t iterations, double omega,
                                                                      const at::Tensor& g) {
  constexpr const char* op = "ams_torch_cuda::sweeps_adjoint";
  const SweepsInputs in = check_sweeps_inputs(op, src, coef, w, nbr, iterations, &g);
  TORCH_CHECK(in.src.is_cuda(), op, ": CUDA tensors expected");
  at::globalContext().alertNotDeterministic("ams_torch_cuda::sweeps_adjoint (float atomicAdd in the scatter)");
  const c10::cuda::CUDAGuard guard(in.src.device());
  at::Tensor g_src = at::zeros({in.slots}, in.src.options()), g_coef = at::zeros({in.slots}, in.src.options());
  at::Tensor g_w = at::zeros({kSweepDirs, in.slots}, in.src.options());
  at::Tensor ws = at::empty({sweeps_cuda_workspace_elems(in.slots, iterations, true)}, in.src.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(in.src.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.src.scalar_type(), op, [&] {
    err = sweeps_adjoint_cuda<scalar_t>(in.src.const_data_ptr<scalar_t>(), in.coef.const_data_ptr<scalar_t>(),
                                        in.w.const_data_ptr<scalar_t>(), in.nbr.const_data_ptr<int64_t>(), in.slots,
                                        iterations, scalar_t(1.0 - omega), in.g.const_data_ptr<scalar_t>(),
                                        g_src.mutable_data_ptr<scalar_t>(), g_coef.mutable_data_ptr<scalar_t>(),
                                        g_w.mutable_data_ptr<scalar_t>(), ws.mutable_data_ptr<scalar_t>(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {g_src, g_coef, g_w.reshape(w.sizes())};
}

} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::grid::kSweepsSchema);
  m.def(ams_torch::grid::kSweepsAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("sweeps", &ams_torch::grid::sweeps_cuda_op);
  m.impl("sweeps_adjoint", &ams_torch::grid::sweeps_adjoint_cuda_op);
}
