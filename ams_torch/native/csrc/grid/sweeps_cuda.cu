// CUDA kernels of the pressure sweeps and their adjoint (sweeps.h; the CPU kernels in
// sweeps_cpu.cpp run the same per-slot code). One thread per list slot; a launch per sweep (the
// sweeps are Jacobi: every slot reads the previous φ), the adjoint's scatter by atomicAdd.
// No torch headers: see sweeps_cuda.h.
#include <cuda_runtime.h>

#include <stdint.h>

#include "grid/sweeps.h"
#include "grid/sweeps_cuda.h"

namespace ams_torch {
namespace grid {
namespace {

constexpr int kSweepThreads = 256;

template <class T>
__global__ void __launch_bounds__(kSweepThreads) fill_kernel(T* out, T value, int64_t n) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) out[i] = value;
}

template <class T>
__global__ void __launch_bounds__(kSweepThreads) sweep_kernel(const T* src, const T* coef, const T* w,
                                                               const int64_t* nbr, int64_t n1, T keep, const T* phi,
                                                               T* out) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n1) out[i] = sweep_cell(i, n1, src, coef, w, nbr, phi, keep);
}

template <class T>
__global__ void __launch_bounds__(kSweepThreads) cell_adjoint_kernel(const T* src, const T* coef, const T* w,
                                                                      const int64_t* nbr, int64_t n1, T keep,
                                                                      const T* phi, const T* g, T* g_src, T* g_coef,
                                                                      T* g_w, T* t, T* g_phi) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n1) sweep_cell_adjoint(i, n1, src, coef, w, nbr, phi, keep, g, g_src, g_coef, g_w, t, g_phi);
}

template <class T>
__global__ void __launch_bounds__(kSweepThreads) scatter_kernel(const T* w, const int64_t* nbr, int64_t n1,
                                                                 const T* t, T* g_phi) {
  const int64_t e = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (e < kSweepDirs * n1) atomicAdd(g_phi + nbr[e], w[e] * t[e % n1]);
}

unsigned blocks_for(int64_t n) { return unsigned((n + kSweepThreads - 1) / kSweepThreads); }

template <class T>
cudaError_t run_forward(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t n1, int64_t iterations,
                        T keep, T* a, T* b, T* history, cudaStream_t stream) {
  // a: φ before the sweep; b: after; history (iterations × n1) or null. Leaves the result in a.
  fill_kernel<T><<<blocks_for(n1), kSweepThreads, 0, stream>>>(a, T(0), n1);
  for (int64_t k = 0; k < iterations; ++k) {
    if (history != nullptr) {
      const cudaError_t err = cudaMemcpyAsync(history + k * n1, a, size_t(n1) * sizeof(T), cudaMemcpyDeviceToDevice,
                                              stream);
      if (err != cudaSuccess) return err;
    }
    sweep_kernel<T><<<blocks_for(n1), kSweepThreads, 0, stream>>>(src, coef, w, nbr, n1, keep, a, b);
    T* tmp = a;
    a = b;
    b = tmp;
  }
  if (iterations % 2 == 1) { // the result is in the caller's b: copy it back into a
    return cudaMemcpyAsync(b, a, size_t(n1) * sizeof(T), cudaMemcpyDeviceToDevice, stream);
  }
  return cudaGetLastError();
}

} // namespace

int64_t sweeps_cuda_workspace_elems(int64_t slots, int64_t iterations, bool adjoint) {
  return adjoint ? (iterations + 4) * slots : 2 * slots;
}

template <class T>
cudaError_t sweeps_cuda(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t slots,
                        int64_t iterations, T keep, T* out, T* workspace, cudaStream_t stream) {
  if (slots <= 0) return cudaSuccess;
  cudaError_t err = run_forward<T>(src, coef, w, nbr, slots, iterations, keep, workspace, workspace + slots, nullptr,
                                   stream);
  if (err != cudaSuccess) return err;
  err = cudaMemcpyAsync(out, workspace, size_t(slots) * sizeof(T), cudaMemcpyDeviceToDevice, stream);
  if (err != cudaSuccess) return err;
  return cudaGetLastError();
}

template <class T>
cudaError_t sweeps_adjoint_cuda(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t slots,
                                int64_t iterations, T keep, const T* g, T* g_src, T* g_coef, T* g_w, T* workspace,
                                cudaStream_t stream) {
  if (slots <= 0) return cudaSuccess;
  const int64_t n1 = slots;
  T* history = workspace;
  T* a = history + iterations * n1;
  T* b = a + n1;
  T* t = b + n1;
  T* g_phi = t + n1;
  cudaError_t err = run_forward<T>(src, coef, w, nbr, n1, iterations, keep, a, b, history, stream);
  if (err != cudaSuccess) return err;
  // the adjoint of φ, ping-ponged between a and b
  err = cudaMemcpyAsync(a, g, size_t(n1) * sizeof(T), cudaMemcpyDeviceToDevice, stream);
  if (err != cudaSuccess) return err;
  T* gcur = a;
  for (int64_t k = iterations - 1; k >= 0; --k) {
    cell_adjoint_kernel<T><<<blocks_for(n1), kSweepThreads, 0, stream>>>(src, coef, w, nbr, n1, keep,
                                                                         history + k * n1, gcur, g_src, g_coef, g_w,
                                                                         t, g_phi);
    scatter_kernel<T><<<blocks_for(kSweepDirs * n1), kSweepThreads, 0, stream>>>(w, nbr, n1, t, g_phi);
    T* tmp = gcur; // the adjoint of this sweep's input is the next one's output adjoint
    gcur = g_phi;
    g_phi = tmp;
  }
  return cudaGetLastError();
}

template cudaError_t sweeps_cuda<float>(const float*, const float*, const float*, const int64_t*, int64_t, int64_t,
                                        float, float*, float*, cudaStream_t);
template cudaError_t sweeps_cuda<double>(const double*, const double*, const double*, const int64_t*, int64_t,
                                         int64_t, double, double*, double*, cudaStream_t);
template cudaError_t sweeps_adjoint_cuda<float>(const float*, const float*, const float*, const int64_t*, int64_t,
                                                int64_t, float, const float*, float*, float*, float*, float*,
                                                cudaStream_t);
template cudaError_t sweeps_adjoint_cuda<double>(const double*, const double*, const double*, const int64_t*, int64_t,
                                                 int64_t, double, const double*, double*, double*, double*, double*,
                                                 cudaStream_t);

} // namespace grid
} // namespace ams_torch
