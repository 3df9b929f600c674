// Torch binding of the CUDA kernels of the differentiable frame: ops
// `ams_torch_cuda::frame_posed` and `frame_adjoint` (schemas and shapes in
// frame_adjoint_binding.h). Built only against a CUDA torch (it needs torch's CUDA headers); the
// kernels are in frame_adjoint_cuda.cu, which nvcc compiles without torch headers. Runs on the
// current CUDA stream of the inputs' device with its workspace from torch's caching allocator; no
// host synchronisation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <optional>
#include <tuple>
#include <vector>

#include "frame/frame_adjoint_binding.h"
#include "frame/frame_adjoint_cuda.h"

namespace ams_torch {
namespace frame {

namespace {

constexpr const char* kPosedOp = "ams_torch_cuda::frame_posed";
constexpr const char* kAdjointOp = "ams_torch_cuda::frame_adjoint";

// Run the kernels of one call (adjoint null: the forward into x, v).
void launch(const char* op, const PosedInputs& in, at::Tensor* x, at::Tensor* v, std::vector<at::Tensor>* out,
            const at::Tensor* xb, const at::Tensor* vb) {
  const at::Tensor& x0 = in.frame.state[kX];
  const FrameSettings& cfg = in.frame.settings;
  at::Tensor workspace = at::empty(
      {frame_adjoint_cuda_workspace_elems(in.frame.scenes, in.frame.strands, in.frame.particles, cfg.substeps)},
      x0.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x0.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x0.scalar_type(), "ams_torch_cuda", [&] {
    const FrameArgs<scalar_t> args = frame_args<scalar_t>(in.frame);
    const scalar_t* poses = in.poses.const_data_ptr<scalar_t>();
    if (out == nullptr) {
      err = frame_adjoint_cuda<scalar_t>(args, cfg, poses, in.pose_scenes, x->mutable_data_ptr<scalar_t>(),
                                         v->mutable_data_ptr<scalar_t>(), nullptr,
                                         workspace.mutable_data_ptr<scalar_t>(), stream);
      return;
    }
    const AdjointPointers<scalar_t> p = adjoint_pointers<scalar_t>(*out, *xb, *vb);
    AdjointBuffers<scalar_t> buf{p.xb_in, p.vb_in, p.xb, p.vb, p.gb, p.extb, p.massb, p.dragb,
                                 {p.stiffb[0], p.stiffb[1], p.stiffb[2]}, p.integrityb, p.angularb, p.poseb,
                                 p.sagb, p.lawb};
    err = frame_adjoint_cuda<scalar_t>(args, cfg, poses, in.pose_scenes, nullptr, nullptr, &buf,
                                       workspace.mutable_data_ptr<scalar_t>(), stream);
  });
  TORCH_CHECK(err == cudaSuccess, op, ": kernel launch failed: ", cudaGetErrorString(err));
}

std::tuple<at::Tensor, at::Tensor> frame_posed_cuda(at::TensorList state, const std::optional<at::Tensor>& ext,
                                                    at::TensorList model,
                                                        const at::Tensor& poses AMS_FRAME_SETTINGS_PARAMS) {
  TORCH_CHECK(state.size() > 0 && state[0].is_cuda(), kPosedOp, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(state[0].device());
  const PosedInputs in = check_posed_inputs(kPosedOp, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS);
  at::Tensor x, v;
  std::tie(x, v) = frame_outputs(in.frame);
  if (in.frame.scenes > 0 && in.frame.strands > 0) launch(kPosedOp, in, &x, &v, nullptr, nullptr, nullptr);
  return {x, v};
}

std::vector<at::Tensor> frame_adjoint_cuda_op(at::TensorList state, const std::optional<at::Tensor>& ext,
                                              at::TensorList model, const at::Tensor& poses AMS_FRAME_SETTINGS_PARAMS,
                                                  const at::Tensor& x_bar,
                                              const at::Tensor& v_bar) {
  TORCH_CHECK(state.size() > 0 && state[0].is_cuda(), kAdjointOp, ": CUDA tensors expected");
  const c10::cuda::CUDAGuard guard(state[0].device());
  const PosedInputs in = check_posed_inputs(kAdjointOp, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS);
  check_adjoint_seeds(kAdjointOp, in, x_bar, v_bar);
  const at::Tensor xb = x_bar.contiguous(), vb = v_bar.contiguous();
  std::vector<at::Tensor> out = adjoint_outputs(in);
  if (in.frame.scenes > 0 && in.frame.strands > 0) launch(kAdjointOp, in, nullptr, nullptr, &out, &xb, &vb);
  return out;
}

} // namespace

} // namespace frame
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::frame::kFramePosedSchema);
  m.def(ams_torch::frame::kFrameAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("frame_posed", &ams_torch::frame::frame_posed_cuda);
  m.impl("frame_adjoint", &ams_torch::frame::frame_adjoint_cuda_op);
}
