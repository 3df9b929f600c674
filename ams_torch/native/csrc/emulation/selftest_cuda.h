// Self-test kernels of the CUDA emulation (csrc/emulation): shared memory and __syncthreads, warp
// collectives, atomics, launch limits, the warp-aggregated add of common/. The same file
// builds for a GPU (backend "selftest_cuda", run by scripts/validate_cuda.py) and for the
// emulation ("selftest_cuda_emu", tests/test_cuda_emulation.py), so the emulator's answers are
// checked against the hardware's on the first GPU run. No torch headers.
#pragma once

#include <cuda_runtime_api.h>
#include <stddef.h>
#include <stdint.h>

namespace ams_torch {
namespace emu_selftest {

extern "C++" {

constexpr int kWarpResults = 14; // values per thread written by warp_ops (see selftest_cuda.cu)

// out[0] = sum of x[0..n) by shared-memory tree reductions in `blocks` blocks of 256 threads
// (grid-stride), one atomicAdd per block. out must hold 0 on entry.
cudaError_t block_sum(const double* x, int64_t n, unsigned blocks, double* out, cudaStream_t stream);

// One block of `threads` threads; thread t writes kWarpResults values at out[t * kWarpResults].
cudaError_t warp_ops(int threads, int64_t* out, cudaStream_t stream);

// blocks × threads threads, each: counter += 1, fsum += 0.5f, dsum += 0.25 (atomics).
cudaError_t atomics(unsigned blocks, int threads, unsigned long long* counter, float* fsum, double* dsum,
                    cudaStream_t stream);

// An empty kernel launched with this configuration: returns the launch's error.
cudaError_t launch(dim3 grid, dim3 block, size_t shared, cudaStream_t stream);

// out[index[i]] += values[i] for i < n by warp_aggregated_add, `threads` per block, grid-stride
// over at most `blocks` blocks.
cudaError_t warp_add(const double* values, const int64_t* index, int64_t n, double* out, int threads,
                     unsigned blocks, cudaStream_t stream);

// Undefined behaviour that only the emulation runs (and must report): mode 1, the threads of a
// block wait at two different __syncthreads(); mode 2, half of them exit before one; mode 3, half
// of a warp calls __syncwarp(0xffffffff). flag: 64 ints of scratch.
cudaError_t bad_barrier(int mode, int* flag, cudaStream_t stream);

} // extern "C++"

} // namespace emu_selftest
} // namespace ams_torch
