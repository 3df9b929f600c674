// Self-test kernels of the CUDA emulation: see selftest_cuda.h.
#include <cuda_runtime.h>

#include <stdint.h>

#include "common/launch_cuda.cuh"
#include "emulation/selftest_cuda.h"
#include "common/warp_atomic_cuda.cuh"

namespace ams_torch {
namespace emu_selftest {
namespace {

constexpr int kSumThreads = 256;

__global__ void block_sum_kernel(const double* x, int64_t n, double* out) {
  __shared__ double part[kSumThreads];
  double s = 0.0;
  for (int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; i < n; i += int64_t(gridDim.x) * blockDim.x)
    s += x[i];
  part[threadIdx.x] = s;
  __syncthreads();
  for (unsigned half = blockDim.x / 2; half > 0; half /= 2) {
    if (threadIdx.x < half) part[threadIdx.x] += part[threadIdx.x + half];
    __syncthreads();
  }
  if (threadIdx.x == 0) atomicAdd(out, part[0]);
}

// Per thread (lane l of warp w): 0 l; 1 __activemask() (converged); 2 __activemask() in `l < 20`
// (else -1); 3 ballot(l % 3 == 0); 4 shfl(10 l, (l + 1) % 32); 5 shfl_down(10 l, 3); 6 shfl_xor(10 l,
// 5); 7 shfl_up(10 l, 2, width 16); 8 match_any(l / 4); 9 any(l == 7); 10 all(l < 100); 11 in `l`
// even (else -1): match_any(__activemask(), l / 8); 12 after __syncwarp, the lane (l + 1) % 32 of
// its warp wrote 100 + that lane to shared memory (-1 when absent); 13 the block's sum of t
// (shared memory, __syncthreads).
__global__ void warp_ops_kernel(int64_t* out) {
  __shared__ int64_t slot[1024];
  __shared__ int64_t total;
  const unsigned t = threadIdx.x;
  const unsigned lane = t % 32u;
  int64_t* o = out + int64_t(t) * kWarpResults;
  const unsigned full = __activemask();
  o[0] = lane;
  o[1] = full;
  o[2] = -1;
  if (lane < 20) o[2] = __activemask();
  o[3] = __ballot_sync(full, lane % 3 == 0);
  o[4] = __shfl_sync(full, int(10 * lane), int((lane + 1) % 32));
  o[5] = __shfl_down_sync(full, int(10 * lane), 3);
  o[6] = __shfl_xor_sync(full, int(10 * lane), 5);
  o[7] = __shfl_up_sync(full, int(10 * lane), 2, 16);
  o[8] = __match_any_sync(full, int(lane / 4));
  o[9] = __any_sync(full, lane == 7);
  o[10] = __all_sync(full, lane < 100);
  o[11] = -1;
  if (lane % 2 == 0) o[11] = __match_any_sync(__activemask(), int(lane / 8));
  slot[t] = 100 + lane;
  __syncwarp(full);
  const unsigned src = (lane + 1) % 32u;
  o[12] = (full >> src & 1u) ? slot[t - lane + src] : -1;
  if (t == 0) total = 0;
  __syncthreads();
  atomicAdd(reinterpret_cast<unsigned long long*>(&total), (unsigned long long)t);
  __syncthreads();
  o[13] = total;
}

__global__ void atomics_kernel(unsigned long long* counter, float* fsum, double* dsum) {
  atomicAdd(counter, 1ull);
  atomicAdd(fsum, 0.5f);
  atomicAdd(dsum, 0.25);
}

__global__ void empty_kernel() {}

__global__ void warp_add_kernel(const double* values, const int64_t* index, int64_t n, double* out) {
  for (int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; i < n; i += int64_t(gridDim.x) * blockDim.x)
    cuda::warp_aggregated_add(out + index[i], values[i]);
}

__global__ void bad_barrier_kernel(int mode, int* flag) {
  if (mode == 1) {
    if (threadIdx.x % 2 == 0) {
      __syncthreads();
      flag[threadIdx.x] = 1;
    } else {
      flag[threadIdx.x] = 2;
      __syncthreads();
    }
  } else if (mode == 2) {
    if (threadIdx.x >= 16) return;
    __syncthreads();
  } else if (mode == 3) {
    if (threadIdx.x % 32 < 16) __syncwarp(0xffffffffu);
  }
}

} // namespace

cudaError_t block_sum(const double* x, int64_t n, unsigned blocks, double* out, cudaStream_t stream) {
  block_sum_kernel<<<blocks, kSumThreads, 0, stream>>>(x, n, out);
  return cudaGetLastError();
}

cudaError_t warp_ops(int threads, int64_t* out, cudaStream_t stream) {
  warp_ops_kernel<<<1, unsigned(threads), 0, stream>>>(out);
  return cudaGetLastError();
}

cudaError_t atomics(unsigned blocks, int threads, unsigned long long* counter, float* fsum, double* dsum,
                    cudaStream_t stream) {
  atomics_kernel<<<blocks, unsigned(threads), 0, stream>>>(counter, fsum, dsum);
  return cudaGetLastError();
}

cudaError_t launch(dim3 grid, dim3 block, size_t shared, cudaStream_t stream) {
  empty_kernel<<<grid, block, shared, stream>>>();
  return cudaGetLastError();
}

cudaError_t warp_add(const double* values, const int64_t* index, int64_t n, double* out, int threads,
                     unsigned blocks, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  const unsigned grid = cuda::grid_stride_blocks(n, threads);
  warp_add_kernel<<<grid < blocks ? grid : blocks, unsigned(threads), 0, stream>>>(values, index, n, out);
  return cudaGetLastError();
}

cudaError_t bad_barrier(int mode, int* flag, cudaStream_t stream) {
  bad_barrier_kernel<<<1, 64, 0, stream>>>(mode, flag);
  return cudaGetLastError();
}

} // namespace emu_selftest
} // namespace ams_torch
