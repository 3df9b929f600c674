// Torch binding of the CUDA adjoint of the collision stage: op `ams_torch_cuda::collide_adjoint`
// (schema and shapes in collide_binding.h). Built only against a CUDA torch; the kernels are in
// collide_adjoint_cuda.cu (nvcc, no torch headers). Runs on the current CUDA stream of the inputs'
// device, workspace from torch's caching allocator, no host synchronisation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <tuple>

#include "collide/collide_adjoint.h"
#include "collide/collide_adjoint_cuda.h"
#include "collide/collide_binding.h"

namespace ams_torch {
namespace collide {

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> collide_adjoint_cuda_op(
    const at::Tensor& x, const at::Tensor& v, at::TensorList model, const at::Tensor& head, at::TensorList tensors,
    at::TensorList poses, c10::IntArrayRef ints, c10::ArrayRef<double> floats, double dt, int64_t rounds,
    bool inextensibility, double ftl_damping, const at::Tensor& x_bar, const at::Tensor& v_bar) {
  constexpr const char* op = "ams_torch_cuda::collide_adjoint";
  const CollideInputs in = check_collide_inputs(op, x, v, model, head, tensors, poses, ints, floats, dt, rounds,
                                                inextensibility, ftl_damping);
  TORCH_CHECK(in.x.is_cuda(), op, ": CUDA tensors expected");
  const auto [gx, gv] = check_adjoint_inputs(op, in, x_bar, v_bar, kMaxPushout);
  const c10::cuda::CUDAGuard guard(in.x.device());
  const auto opts = in.x.options().memory_format(at::MemoryFormat::Contiguous);
  at::Tensor gxo = at::empty(in.x.sizes(), opts), gvo = at::empty(in.x.sizes(), opts);
  at::Tensor gcol = at::zeros({in.scenes, in.strands, in.count, kPoseGrads}, opts);
  at::Tensor ghead = at::zeros({in.scenes, in.strands, 9}, opts);
  if (in.scenes == 0 || in.strands == 0) return {gxo, gvo, gcol, ghead};
  const int64_t used_rounds = in.settings.inextensibility ? in.settings.rounds : 0;
  at::Tensor workspace = at::empty({collide_adjoint_cuda_workspace_elems(in.scenes, in.strands, in.particles, in.count,
                                                                         used_rounds, int64_t(in.x.element_size()))},
                                   in.x.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(in.x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
    err = collide_adjoint_cuda<scalar_t>(collide_args<scalar_t>(in), in.settings, gx.const_data_ptr<scalar_t>(),
                                         gv.const_data_ptr<scalar_t>(), gxo.mutable_data_ptr<scalar_t>(),
                                         gvo.mutable_data_ptr<scalar_t>(), gcol.mutable_data_ptr<scalar_t>(),
                                         ghead.mutable_data_ptr<scalar_t>(), workspace.mutable_data_ptr<scalar_t>(),
                                         stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {gxo, gvo, gcol, ghead};
}

} // namespace collide
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::collide::kCollideAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("collide_adjoint", &ams_torch::collide::collide_adjoint_cuda_op);
}
