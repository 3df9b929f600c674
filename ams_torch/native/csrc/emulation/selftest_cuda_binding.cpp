// Torch binding of the CUDA emulation's self-test kernels (selftest_cuda.h): ops of
// `ams_torch_selftest_cuda` (on a GPU) and `ams_torch_selftest_cuda_emu` (the emulation, CPU
// tensors). A launch error raises, with the emulator's detail when emulated.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/cat.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "emulation/selftest_cuda.h"

namespace ams_torch {
namespace emu_selftest {
namespace {

cudaStream_t stream_of(const at::Tensor& t) { return c10::cuda::getCurrentCUDAStream(t.device().index()).stream(); }

void check(cudaError_t err, const char* op) {
  TORCH_CHECK(err == cudaSuccess, "ams_torch_selftest_cuda::", op, ": ", cudaGetErrorString(err));
}

at::Tensor block_sum_op(const at::Tensor& x, int64_t blocks) {
  TORCH_CHECK(x.is_cuda() && x.scalar_type() == at::kDouble, "block_sum: a float64 CUDA tensor");
  const c10::cuda::CUDAGuard guard(x.device());
  const at::Tensor xc = x.contiguous();
  at::Tensor out = at::zeros({1}, x.options());
  check(block_sum(xc.const_data_ptr<double>(), xc.numel(), unsigned(blocks), out.mutable_data_ptr<double>(),
                  stream_of(x)),
        "block_sum");
  return out;
}

at::Tensor warp_ops_op(const at::Tensor& like, int64_t threads) {
  TORCH_CHECK(like.is_cuda(), "warp_ops: `like` must be a CUDA tensor");
  const c10::cuda::CUDAGuard guard(like.device());
  at::Tensor out = at::empty({threads, kWarpResults}, like.options().dtype(at::kLong));
  check(warp_ops(int(threads), out.mutable_data_ptr<int64_t>(), stream_of(like)), "warp_ops");
  return out;
}

at::Tensor atomics_op(const at::Tensor& like, int64_t blocks, int64_t threads) {
  TORCH_CHECK(like.is_cuda(), "atomics: `like` must be a CUDA tensor");
  const c10::cuda::CUDAGuard guard(like.device());
  at::Tensor counter = at::zeros({1}, like.options().dtype(at::kLong));
  at::Tensor fsum = at::zeros({1}, like.options().dtype(at::kFloat));
  at::Tensor dsum = at::zeros({1}, like.options().dtype(at::kDouble));
  check(atomics(unsigned(blocks), int(threads), reinterpret_cast<unsigned long long*>(counter.mutable_data_ptr<int64_t>()),
                fsum.mutable_data_ptr<float>(), dsum.mutable_data_ptr<double>(), stream_of(like)),
        "atomics");
  return at::cat({counter.to(at::kDouble), fsum.to(at::kDouble), dsum});
}

void launch_op(const at::Tensor& like, at::IntArrayRef grid, at::IntArrayRef block, int64_t shared) {
  TORCH_CHECK(like.is_cuda() && grid.size() == 3 && block.size() == 3, "launch: a CUDA tensor, grid and block (3,)");
  const c10::cuda::CUDAGuard guard(like.device());
  check(launch(dim3(unsigned(grid[0]), unsigned(grid[1]), unsigned(grid[2])),
               dim3(unsigned(block[0]), unsigned(block[1]), unsigned(block[2])), size_t(shared), stream_of(like)),
        "launch");
}

at::Tensor warp_add_op(const at::Tensor& values, const at::Tensor& index, int64_t size, int64_t threads,
                       int64_t blocks) {
  TORCH_CHECK(values.is_cuda() && values.scalar_type() == at::kDouble && index.scalar_type() == at::kLong &&
                  index.device() == values.device() && index.numel() == values.numel(),
              "warp_add: float64 values and int64 indices of one size on one CUDA device");
  const c10::cuda::CUDAGuard guard(values.device());
  const at::Tensor v = values.contiguous(), i = index.contiguous();
  at::Tensor out = at::zeros({size}, values.options());
  check(warp_add(v.const_data_ptr<double>(), i.const_data_ptr<int64_t>(), v.numel(), out.mutable_data_ptr<double>(),
                 int(threads), unsigned(blocks), stream_of(values)),
        "warp_add");
  return out;
}

void bad_barrier_op(const at::Tensor& like, int64_t mode) {
  TORCH_CHECK(like.is_cuda(), "bad_barrier: `like` must be a CUDA tensor");
  at::Tensor flag = at::zeros({64}, like.options().dtype(at::kInt));
  check(bad_barrier(int(mode), flag.mutable_data_ptr<int>(), stream_of(like)), "bad_barrier");
}

} // namespace
} // namespace emu_selftest
} // namespace ams_torch

TORCH_LIBRARY(ams_torch_selftest_cuda, m) {
  m.def("block_sum(Tensor x, int blocks) -> Tensor");
  m.def("warp_ops(Tensor like, int threads) -> Tensor");
  m.def("atomics(Tensor like, int blocks, int threads) -> Tensor");
  m.def("launch(Tensor like, int[] grid, int[] block, int shared) -> ()");
  m.def("warp_add(Tensor values, Tensor index, int size, int threads, int blocks) -> Tensor");
  m.def("bad_barrier(Tensor like, int mode) -> ()");
}

TORCH_LIBRARY_IMPL(ams_torch_selftest_cuda, CUDA, m) {
  m.impl("block_sum", &ams_torch::emu_selftest::block_sum_op);
  m.impl("warp_ops", &ams_torch::emu_selftest::warp_ops_op);
  m.impl("atomics", &ams_torch::emu_selftest::atomics_op);
  m.impl("launch", &ams_torch::emu_selftest::launch_op);
  m.impl("warp_add", &ams_torch::emu_selftest::warp_add_op);
  m.impl("bad_barrier", &ams_torch::emu_selftest::bad_barrier_op);
}
