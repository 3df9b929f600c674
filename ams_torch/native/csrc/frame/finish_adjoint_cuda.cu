// CUDA kernels of the finish and yield adjoints (finish_adjoint.h; the CPU kernels in
// finish_adjoint_cpu.cpp run the same per-strand and per-particle code). No torch headers.
#include <cuda_runtime.h>

#include <stdint.h>

#include "common/launch_cuda.cuh"
#include "frame/finish_adjoint.h"
#include "frame/finish_adjoint_cuda.h"

namespace ams_torch {
namespace frame {
namespace {

constexpr int kThreads = 256;

template <class T>
__global__ void finish_adjoint_kernel(const FinishArgs<T> args, const T* g_out, const T* g_speed, T* g_x, T* g_v,
                                      T* g_pose, int64_t strands) {
  for (int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; g < strands; g += int64_t(gridDim.x) * blockDim.x)
    finish_adjoint_strand(args, g, g_out, g_speed, g_x, g_v, g_pose);
}

template <class T>
__global__ void yield_adjoint_kernel(const T* x, const T* anchor, const T* limit, const bool* free, const T* g_new,
                                     T* g_x, T* g_anchor, T* g_limit, int64_t count, int64_t strands,
                                     int64_t particles) {
  const int64_t per_scene = strands * particles;
  for (int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; p < count; p += int64_t(gridDim.x) * blockDim.x) {
    const int64_t e = p % per_scene;
    yield_adjoint_particle(x + 3 * p, anchor + 3 * p, limit[e], free[e], g_new + 3 * p, g_x + 3 * p,
                           g_anchor + 3 * p, g_limit + p);
  }
}

} // namespace

template <class T>
cudaError_t finish_adjoint_cuda(const FinishArgs<T>& args, const T* g_out, const T* g_speed, T* g_x, T* g_v,
                                T* g_pose, cudaStream_t stream) {
  const int64_t strands = args.scenes * args.strands;
  if (strands == 0 || args.particles == 0) return cudaSuccess;
  finish_adjoint_kernel<T><<<cuda::grid_stride_blocks(strands, kThreads), kThreads, 0, stream>>>(
      args, g_out, g_speed, g_x, g_v, g_pose, strands);
  return cudaGetLastError();
}

template <class T>
cudaError_t yield_adjoint_cuda(const T* x, const T* anchor, const T* limit, const bool* free, const T* g_new, T* g_x,
                               T* g_anchor, T* g_limit, int64_t count, int64_t strands, int64_t particles,
                               cudaStream_t stream) {
  if (count == 0) return cudaSuccess;
  yield_adjoint_kernel<T><<<cuda::grid_stride_blocks(count, kThreads), kThreads, 0, stream>>>(
      x, anchor, limit, free, g_new, g_x, g_anchor, g_limit, count, strands, particles);
  return cudaGetLastError();
}

template cudaError_t finish_adjoint_cuda<float>(const FinishArgs<float>&, const float*, const float*, float*, float*,
                                                float*, cudaStream_t);
template cudaError_t finish_adjoint_cuda<double>(const FinishArgs<double>&, const double*, const double*, double*,
                                                 double*, double*, cudaStream_t);
template cudaError_t yield_adjoint_cuda<float>(const float*, const float*, const float*, const bool*, const float*,
                                               float*, float*, float*, int64_t, int64_t, int64_t, cudaStream_t);
template cudaError_t yield_adjoint_cuda<double>(const double*, const double*, const double*, const bool*,
                                                const double*, double*, double*, double*, int64_t, int64_t, int64_t,
                                                cudaStream_t);

} // namespace frame
} // namespace ams_torch
