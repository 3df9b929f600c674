// Torch binding of the CUDA banded strand solve: op `ams_torch_cuda::solve_banded(blocks, rhs)`.
// Built only against a CUDA torch (it needs torch's CUDA headers); the kernel itself is in
// banded_cuda.cu, which nvcc compiles without torch headers. Runs on the current CUDA stream of
// the inputs' device, with its workspace from torch's caching allocator.
//
//   blocks: (..., N, 4, 3, 3) float32/float64 on one CUDA device; rhs: (..., N, 3) same dtype
//   and device. Returns x: (..., N, 3), contiguous.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "banded/banded_cuda.h"

namespace ams_torch {
namespace banded {

at::Tensor solve_banded_cuda_op(const at::Tensor& blocks, const at::Tensor& rhs) {
  TORCH_CHECK(blocks.dim() >= 4 && blocks.size(-1) == 3 && blocks.size(-2) == 3 && blocks.size(-3) == 4,
              "ams_torch_cuda::solve_banded: blocks must have shape (..., N, 4, 3, 3), got ", blocks.sizes());
  TORCH_CHECK(rhs.dim() == blocks.dim() - 2 && rhs.size(-1) == 3 &&
                  rhs.sizes().slice(0, rhs.dim() - 1) == blocks.sizes().slice(0, blocks.dim() - 3),
              "ams_torch_cuda::solve_banded: rhs must have shape (..., N, 3) matching blocks ", blocks.sizes(),
              ", got ", rhs.sizes());
  TORCH_CHECK(blocks.is_cuda() && rhs.is_cuda() && blocks.device() == rhs.device(),
              "ams_torch_cuda::solve_banded: blocks and rhs must be on the same CUDA device");
  TORCH_CHECK(blocks.scalar_type() == rhs.scalar_type(),
              "ams_torch_cuda::solve_banded: blocks and rhs must have the same dtype, got ", blocks.scalar_type(),
              " and ", rhs.scalar_type());
  const c10::cuda::CUDAGuard guard(rhs.device());
  const at::Tensor b = blocks.contiguous();
  const at::Tensor r = rhs.contiguous();
  at::Tensor x = at::empty(rhs.sizes(), rhs.options().memory_format(at::MemoryFormat::Contiguous));
  const int64_t n = blocks.size(-4);
  if (x.numel() == 0) return x;
  const int64_t strands = r.numel() / (n * 3);
  at::Tensor workspace = at::empty({cuda_workspace_elems(strands, n)}, rhs.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(rhs.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(r.scalar_type(), "ams_torch_cuda::solve_banded", [&] {
    err = solve_banded_cuda<scalar_t>(b.const_data_ptr<scalar_t>(), r.const_data_ptr<scalar_t>(),
                                      x.mutable_data_ptr<scalar_t>(), workspace.mutable_data_ptr<scalar_t>(), strands,
                                      n, stream);
  });
  TORCH_CHECK(err == cudaSuccess, "ams_torch_cuda::solve_banded: kernel launch failed: ", cudaGetErrorString(err));
  return x;
}

} // namespace banded
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def("solve_banded(Tensor blocks, Tensor rhs) -> Tensor");
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("solve_banded", &ams_torch::banded::solve_banded_cuda_op);
}
