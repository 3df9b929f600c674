// Torch binding of the CUDA finish and yield adjoints: ops `ams_torch_cuda::finish_adjoint` and
// `yield_adjoint` (schemas in finish_adjoint_binding.h). Built only against a CUDA torch; the kernels
// are in finish_adjoint_cuda.cu. Current CUDA stream of the inputs' device, no host synchronisation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <optional>
#include <tuple>

#include "frame/finish_adjoint_binding.h"
#include "frame/finish_adjoint_cuda.h"

namespace ams_torch {
namespace frame {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> finish_adjoint_cuda_op(const at::Tensor& x, const at::Tensor& v,
                                                                      const at::Tensor& num_pinned,
                                                                      at::TensorList pose, const at::Tensor& g_v,
                                                                      const std::optional<at::Tensor>& g_speed) {
  constexpr const char* op = "ams_torch_cuda::finish_adjoint";
  const FinishAdjointInputs fa = check_finish_adjoint_inputs(op, x, v, num_pinned, pose, g_v, g_speed);
  const FinishInputs& in = fa.in;
  TORCH_CHECK(in.x.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(in.x.device());
  at::Tensor gx = at::empty(x.sizes(), in.x.options()), gv = at::empty(x.sizes(), in.x.options());
  at::Tensor gp = at::empty({in.scenes * in.strands, 9}, in.x.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(in.x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
    err = finish_adjoint_cuda<scalar_t>(finish_args<scalar_t>(in), fa.g_v.const_data_ptr<scalar_t>(),
                                        fa.g_speed.defined() ? fa.g_speed.const_data_ptr<scalar_t>() : nullptr,
                                        gx.mutable_data_ptr<scalar_t>(), gv.mutable_data_ptr<scalar_t>(),
                                        gp.mutable_data_ptr<scalar_t>(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {gx, gv, gp};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> yield_adjoint_cuda_op(const at::Tensor& x, const at::Tensor& anchor,
                                                                     const at::Tensor& limit, const at::Tensor& free,
                                                                     const at::Tensor& g_new) {
  constexpr const char* op = "ams_torch_cuda::yield_adjoint";
  const YieldInputs in = check_yield_inputs(op, x, anchor, limit, free, g_new);
  TORCH_CHECK(in.x.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(in.x.device());
  at::Tensor gx = at::empty(x.sizes(), in.x.options()), ga = at::empty(x.sizes(), in.x.options());
  at::Tensor gl = at::empty(x.sizes().slice(0, x.dim() - 1), in.x.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(in.x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
    err = yield_adjoint_cuda<scalar_t>(in.x.const_data_ptr<scalar_t>(), in.anchor.const_data_ptr<scalar_t>(),
                                       in.limit.const_data_ptr<scalar_t>(), in.free.const_data_ptr<bool>(),
                                       in.g_new.const_data_ptr<scalar_t>(), gx.mutable_data_ptr<scalar_t>(),
                                       ga.mutable_data_ptr<scalar_t>(), gl.mutable_data_ptr<scalar_t>(), in.count,
                                       in.strands, in.particles, stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {gx, ga, gl};
}

} // namespace
} // namespace frame
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::frame::kFinishAdjointSchema);
  m.def(ams_torch::frame::kYieldAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("finish_adjoint", &ams_torch::frame::finish_adjoint_cuda_op);
  m.impl("yield_adjoint", &ams_torch::frame::yield_adjoint_cuda_op);
}
