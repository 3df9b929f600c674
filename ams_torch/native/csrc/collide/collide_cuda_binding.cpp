// Torch binding of the CUDA fused collision stage: op `ams_torch_cuda::collide` (schema
// and shapes in collide_binding.h). Built only against a CUDA torch; the kernels are in
// collide_cuda.cu (nvcc, no torch headers). Runs on the current CUDA stream of the inputs'
// device, workspace from torch's caching allocator, no host synchronisation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <tuple>

#include "collide/collide_binding.h"
#include "collide/collide_cuda.h"

namespace ams_torch {
namespace collide {

std::tuple<at::Tensor, at::Tensor> collide_cuda_op(const at::Tensor& x, const at::Tensor& v, at::TensorList model,
                                                   const at::Tensor& head, at::TensorList tensors,
                                                   at::TensorList poses, c10::IntArrayRef ints,
                                                   c10::ArrayRef<double> floats, double dt, int64_t rounds,
                                                   bool inextensibility, double ftl_damping) {
  constexpr const char* op = "ams_torch_cuda::collide";
  const CollideInputs in = check_collide_inputs(op, x, v, model, head, tensors, poses, ints, floats, dt, rounds,
                                                inextensibility, ftl_damping);
  TORCH_CHECK(in.x.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(in.x.device());
  const auto opts = in.x.options().memory_format(at::MemoryFormat::Contiguous);
  at::Tensor xo = at::empty(in.x.sizes(), opts), vo = at::empty(in.x.sizes(), opts);
  if (in.scenes == 0 || in.strands == 0) return {xo, vo};
  at::Tensor workspace = at::empty(
      {collide_cuda_workspace_elems(in.scenes, in.strands, in.particles, in.count, int64_t(in.x.element_size()))},
      in.x.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(in.x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
    err = collide_cuda<scalar_t>(collide_args<scalar_t>(in), in.settings, xo.mutable_data_ptr<scalar_t>(),
                                 vo.mutable_data_ptr<scalar_t>(), workspace.mutable_data_ptr<scalar_t>(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {xo, vo};
}

} // namespace collide
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::collide::kCollideSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("collide", &ams_torch::collide::collide_cuda_op);
}
