// CUDA kernels of the hair–hair grid: the arithmetic of grid.h (shared with the CPU kernels),
// launched by the functions of grid_cuda.h. No torch headers (nvcc alone compiles this file).
//
//   P2G: one thread per particle, warp-aggregated atomicAdd of mass and momentum into the faces
//        (summation order, hence the last bits, vary between runs; the binding tells torch's
//        deterministic mode: alertNotDeterministic).
//   pressure: setup over every cell (active cells take a slot of their scene's static-capacity
//        list by atomicAdd; a cell with src > 0 marks its scene as pushing), then ONE launch for
//        all Jacobi sweeps: one block per scene loops over its listed cells, __syncthreads()
//        between sweeps (double-buffered phi, so the result does not depend on the list order);
//        a scene that does not push returns at once (phi stays 0). Then the face field.
//   G2P: one thread per particle, fused with the FLIP/PIC blend and the frame changes.
#include <cuda_runtime.h>

#include <stdint.h>

#include "grid.h"
#include "grid_cuda.h"
#include "launch_cuda.cuh"
#include "warp_atomic_cuda.cuh"

namespace ams_torch {
namespace grid {
namespace {

constexpr int kThreads = 256;       // threads per block of the per-particle / per-cell kernels
constexpr int kSweepThreads = 512;  // threads of the one block per scene of the sweeps

unsigned blocks_for(int64_t n) { return cuda::grid_stride_blocks(n, kThreads); }

template <class T>
struct AtomicAdd {
  AMS_GRID_HD void operator()(T* ptr, T value) const {
#if defined(__CUDA_ARCH__)
    cuda::warp_aggregated_add(ptr, value);
#else
    *ptr += value;
#endif
  }
};

template <class T>
__global__ void p2g_kernel(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int64_t B,
                           int64_t P, int64_t r, T h) {
  const int64_t nf = num_faces(r);
  for (int64_t q = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; q < B * P; q += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = q / P;
    T xl[3], vl[3];
    to_head(frame + 18 * b, x + 3 * q, v + 3 * q, xl, vl);
    p2g_scatter(xl, vl, m[q], origin, h, r, faces + b * 3 * nf * 2, AtomicAdd<T>());
  }
}

template <class T>
__global__ void setup_kernel(const T* faces, const T* rho0, const T* dt, T* entries, int32_t* cells, int32_t* counts,
                             int32_t* pushes, int64_t B, int64_t r, double h, double omega, double stiffness,
                             double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  const int64_t nf = num_faces(r), r3 = r * r * r;
  for (int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; g < B * r3; g += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = g / r3, cell = g % r3;
    const int64_t i = cell / (r * r), j = (cell / r) % r, k = cell % r;
    const T* fs = faces + b * 3 * nf * 2;
    if (!cell_active(fs, r, i, j, k, q.eps)) continue;
    T e[kEntry];
    const T src = cell_entry(fs, r, i, j, k, q, e);
    const int64_t slot = b * r3 + atomicAdd(counts + b, 1);
    for (int s = 0; s < kEntry; ++s) entries[kEntry * slot + s] = e[s];
    cells[slot] = int32_t(cell);
    if (src > T(0)) pushes[b] = 1;
  }
}

template <class T>
__global__ void __launch_bounds__(kSweepThreads) sweep_kernel(const T* entries, const int32_t* cells,
                                                              const int32_t* counts, const int32_t* pushes, T* phi_a,
                                                              T* phi_b, int64_t r, int64_t iterations,
                                                              double one_minus_omega) {
  const int64_t b = blockIdx.x;
  if (pushes[b] == 0) return; // the same for every thread of the block
  const int64_t r3 = r * r * r;
  const int64_t n = counts[b];
  const T keep = T(one_minus_omega);
  T* pa = phi_a + b * r3;
  T* pb = phi_b + b * r3;
  const T* e = entries + kEntry * b * r3;
  const int32_t* cl = cells + b * r3;
  for (int64_t it = 0; it < iterations; ++it) {
    const T* src = (it & 1) ? pb : pa;
    T* dst = (it & 1) ? pa : pb;
    for (int64_t k = threadIdx.x; k < n; k += blockDim.x) {
      const int64_t cell = cl[k];
      const unsigned mask = neighbour_mask(r, cell / (r * r), (cell / r) % r, cell % r);
      dst[cell] = sweep_cell(src, r, cell, mask, e + kEntry * k, keep);
    }
    __syncthreads(); // this sweep's writes are visible to the whole block before the next reads them
  }
}

template <class T>
__global__ void field_kernel(const T* faces, const T* phi, const T* rho0, const T* dt, T* field, int64_t B, int64_t r,
                             double h, double omega, double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  const int64_t nf = num_faces(r), r3 = r * r * r;
  for (int64_t f = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; f < B * 3 * nf;
       f += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = f / (3 * nf);
    const int c = int((f / nf) % 3);
    const int64_t face = f % nf;
    const int64_t n1 = c == 1 ? r + 1 : r, n2 = c == 2 ? r + 1 : r;
    field[f] = face_field(faces + b * 3 * nf * 2, phi + b * r3, r, c, face / (n1 * n2), (face / n2) % n1, face % n2,
                          face, q);
  }
}

template <class T>
__global__ void g2p_kernel(const T* x, const T* v, const T* field, const T* frame, const T* origin, const bool* free,
                           int64_t N, const T* dt, T* xo, T* vo, int64_t B, int64_t P, int64_t r, T h, T pic) {
  const int64_t nf = num_faces(r);
  const T dtv = *dt;
  for (int64_t q = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; q < B * P; q += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = q / P;
    g2p_particle(frame + 18 * b, x + 3 * q, v + 3 * q, field + b * 3 * nf, origin, h, r, pic, free[(q % P) % N], dtv,
                 xo + 3 * q, vo + 3 * q);
  }
}

} // namespace

template <class T>
cudaError_t p2g_cuda(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int64_t B,
                     int64_t P, int64_t r, double h, cudaStream_t stream) {
  cudaError_t err = cudaMemsetAsync(faces, 0, sizeof(T) * size_t(B * 3 * num_faces(r) * 2), stream);
  if (err != cudaSuccess || B * P == 0) return err;
  p2g_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(x, v, m, frame, origin, faces, B, P, r, T(h));
  return cudaGetLastError();
}

template <class T>
cudaError_t pressure_cuda(const T* faces, const T* rho0, const T* dt, T* phi_a, T* phi_b, T* field, T* entries,
                          int32_t* cells, int32_t* counters, int64_t B, int64_t r, double h, int64_t iterations,
                          double omega, double stiffness, double pic, cudaStream_t stream) {
  if (B == 0) return cudaSuccess;
  const int64_t r3 = r * r * r;
  if (B > 0x7fffffffLL || r3 > 0x7fffffffLL) return cudaErrorInvalidValue;
  cudaError_t err = cudaMemsetAsync(phi_a, 0, sizeof(T) * size_t(B * r3), stream);
  if (err == cudaSuccess && phi_b != phi_a) err = cudaMemsetAsync(phi_b, 0, sizeof(T) * size_t(B * r3), stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(counters, 0, sizeof(int32_t) * size_t(2 * B), stream);
  if (err != cudaSuccess) return err;
  if (iterations > 0) {
    setup_kernel<T><<<blocks_for(B * r3), kThreads, 0, stream>>>(faces, rho0, dt, entries, cells, counters,
                                                                 counters + B, B, r, h, omega, stiffness, pic);
    sweep_kernel<T><<<unsigned(B), kSweepThreads, 0, stream>>>(entries, cells, counters, counters + B, phi_a, phi_b, r,
                                                              iterations, 1.0 - omega);
  }
  const T* phi = iterations % 2 == 0 ? phi_a : phi_b;
  field_kernel<T><<<blocks_for(B * 3 * num_faces(r)), kThreads, 0, stream>>>(faces, phi, rho0, dt, field, B, r, h,
                                                                             omega, stiffness, pic);
  return cudaGetLastError();
}

template <class T>
cudaError_t g2p_cuda(const T* x, const T* v, const T* field, const T* frame, const T* origin, const bool* free,
                     int64_t N, const T* dt, T* xo, T* vo, int64_t B, int64_t P, int64_t r, double h, double pic,
                     cudaStream_t stream) {
  if (B * P == 0) return cudaSuccess;
  g2p_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(x, v, field, frame, origin, free, N, dt, xo, vo, B, P, r,
                                                            T(h), T(pic));
  return cudaGetLastError();
}

#define AMS_GRID_INSTANTIATE(T)                                                                                   \
  template cudaError_t p2g_cuda<T>(const T*, const T*, const T*, const T*, const T*, T*, int64_t, int64_t, int64_t, \
                                   double, cudaStream_t);                                                          \
  template cudaError_t pressure_cuda<T>(const T*, const T*, const T*, T*, T*, T*, T*, int32_t*, int32_t*, int64_t, \
                                        int64_t, double, int64_t, double, double, double, cudaStream_t);           \
  template cudaError_t g2p_cuda<T>(const T*, const T*, const T*, const T*, const T*, const bool*, int64_t, const T*, \
                                   T*, T*, int64_t, int64_t, int64_t, double, double, cudaStream_t);
AMS_GRID_INSTANTIATE(float)
AMS_GRID_INSTANTIATE(double)
#undef AMS_GRID_INSTANTIATE

} // namespace grid
} // namespace ams_torch
