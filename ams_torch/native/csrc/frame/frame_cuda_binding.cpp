// Torch binding of the CUDA fused frame kernel: op `ams_torch_cuda::frame` (schema and
// shapes in frame_binding.h). Built only against a CUDA torch (it needs torch's CUDA headers);
// the kernels are in frame_cuda.cu, which nvcc compiles without torch headers. Runs on the
// current CUDA stream of the inputs' device, with its workspace from torch's caching allocator;
// no host synchronisation (capturable by CUDA graphs). Also ops `ams_torch_cuda::finish`
// (finish.h, one launch) and `frame_finish` (the frame, then the finish in place on its v').
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <optional>
#include <tuple>

#include "frame/contact_binding.h"
#include "frame/frame_binding.h"
#include "frame/frame_cuda.h"

namespace ams_torch {
namespace frame {

// Both frame ops: the frame (or one substep's system), and with `finish_pose` the frame's end
// fused in, in place on v' after the frame (third output: the speeds; undefined without).
std::tuple<at::Tensor, at::Tensor, at::Tensor> frame_impl(const char* op, const FrameInputs& in,
                                                          const at::TensorList* finish_pose) {
  const at::Tensor& x = in.state[kX];
  TORCH_CHECK(x.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(x.device());
  at::Tensor out0, out1; // (not structured bindings: C++17 lambdas cannot capture them)
  std::tie(out0, out1) = frame_outputs(in);
  std::optional<FinishInputs> f;
  if (finish_pose != nullptr) f = fused_finish_inputs(op, in, out0, out1, *finish_pose);
  const at::Tensor speed = f ? f->speed : at::Tensor();
  if (in.scenes == 0 || in.strands == 0) return {out0, out1, speed};
  at::Tensor workspace =
      at::empty({frame_cuda_workspace_elems(in.scenes, in.strands, in.particles, in.settings.substeps)}, x.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_cuda::frame", [&] {
    err = frame_cuda<scalar_t>(frame_args<scalar_t>(in), in.settings, in.assemble_substep,
                               out0.mutable_data_ptr<scalar_t>(), out1.mutable_data_ptr<scalar_t>(),
                               workspace.mutable_data_ptr<scalar_t>(), stream);
    if (err == cudaSuccess && f) err = finish_cuda<scalar_t>(finish_args<scalar_t>(*f), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {out0, out1, speed};
}

std::tuple<at::Tensor, at::Tensor> frame_cuda_op(at::TensorList state, const std::optional<at::Tensor>& ext,
                                                 at::TensorList model, at::TensorList poses AMS_FRAME_SETTINGS_PARAMS,
                                                     bool hermite,
                                                 int64_t assemble_substep) {
  constexpr const char* op = "ams_torch_cuda::frame";
  const FrameInputs in = check_frame_inputs(op, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS, hermite,
      assemble_substep);
  const auto out = frame_impl(op, in, nullptr);
  return {std::get<0>(out), std::get<1>(out)};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> frame_finish_cuda_op(
    at::TensorList state, const std::optional<at::Tensor>& ext, at::TensorList model,
        at::TensorList poses AMS_FRAME_SETTINGS_PARAMS, bool hermite, int64_t assemble_substep,
    at::TensorList finish_pose) {
  constexpr const char* op = "ams_torch_cuda::frame_finish";
  const FrameInputs in = check_frame_inputs(op, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS, hermite,
      assemble_substep);
  return frame_impl(op, in, &finish_pose);
}

std::tuple<at::Tensor, at::Tensor> frame_contact_cuda_op(
    at::TensorList state, const std::optional<at::Tensor>& ext, at::TensorList model,
        at::TensorList poses AMS_FRAME_SETTINGS_PARAMS, bool hermite, at::TensorList tensors,
    at::TensorList collider_poses, c10::IntArrayRef ints, c10::ArrayRef<double> floats) {
  constexpr const char* op = "ams_torch_cuda::frame_contact";
  const FrameInputs in = check_frame_inputs(op, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS, hermite, -1);
  const at::Tensor& x = in.state[kX];
  TORCH_CHECK(x.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(x.device());
  const ContactInputs cin = check_contact_inputs(op, in, tensors, collider_poses, ints, floats);
  at::Tensor out0, out1;
  std::tie(out0, out1) = frame_outputs(in);
  if (in.scenes == 0 || in.strands == 0) return {out0, out1};
  at::Tensor workspace =
      at::empty({frame_cuda_workspace_elems(in.scenes, in.strands, in.particles, in.settings.substeps)}, x.options());
  at::Tensor table = at::empty({frame_contact_table_bytes(in.scenes, in.settings.substeps, cin.count,
                                                          int64_t(x.element_size()))},
                               x.options().dtype(at::kByte));
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), op, [&] {
    err = frame_contact_cuda<scalar_t>(frame_args<scalar_t>(in), contact_args<scalar_t>(cin), in.settings,
                                       out0.mutable_data_ptr<scalar_t>(), out1.mutable_data_ptr<scalar_t>(),
                                       workspace.mutable_data_ptr<scalar_t>(), table.mutable_data_ptr(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {out0, out1};
}

std::tuple<at::Tensor, at::Tensor> finish_cuda_op(const at::Tensor& x, const at::Tensor& v,
                                                  const at::Tensor& num_pinned, at::TensorList pose) {
  constexpr const char* op = "ams_torch_cuda::finish";
  TORCH_CHECK(x.is_cuda(), op, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(x.device());
  FinishInputs in = check_finish_inputs(op, x, v, num_pinned, pose);
  if (in.x.numel() == 0) return {in.v_out, in.speed};
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op,
                             [&] { err = finish_cuda<scalar_t>(finish_args<scalar_t>(in), stream); });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
  return {in.v_out, in.speed};
}

} // namespace frame
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::frame::kFrameSchema);
  m.def(ams_torch::frame::kFrameFinishSchema);
  m.def(ams_torch::frame::kFinishSchema);
  m.def(ams_torch::frame::kFrameContactSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("frame_contact", &ams_torch::frame::frame_contact_cuda_op);
  m.impl("frame", &ams_torch::frame::frame_cuda_op);
  m.impl("frame_finish", &ams_torch::frame::frame_finish_cuda_op);
  m.impl("finish", &ams_torch::frame::finish_cuda_op);
}
