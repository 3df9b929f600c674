// Launchers of the CUDA hair–hair grid kernels. Plain pointers and a cudaStream_t, no torch
// headers: grid_cuda.cu compiles with nvcc alone, and the thin torch binding
// (grid_cuda_binding.cpp, built only against a CUDA torch) calls these on the current stream.
// Every launcher is asynchronous (no host synchronisation: capturable by CUDA graphs) and
// returns cudaGetLastError() after its last launch. Shapes and layouts: grid.h.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

namespace ams_torch {
namespace grid {

extern "C++" {

// faces (B, 3, F, 2) = P2G of x, v (B, P, 3), m (B, P) with frame (B, 6, 3), origin (3,).
// Zeroes `faces` first; one thread per particle, atomicAdd into the faces.
template <class T>
cudaError_t p2g_cuda(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int64_t B,
                     int64_t P, int64_t r, double h, cudaStream_t stream);

// phi (B, R, R, R) and field (B, 3, F) from faces (B, 3, F, 2); rho0 and dt are device scalars.
// Workspace (caller-allocated, any content): entries B R^3 8 values of T, cells B R^3 int32,
// counters 2 B int32. phi_a and phi_b (B R^3 each; phi_b may equal phi_a when iterations == 0)
// are zeroed here; the result is in phi_a when `iterations` is even, else in phi_b.
// Launches: setup (every cell; active ones take a slot by atomicAdd), sweeps (one block per
// scene runs all iterations, __syncthreads() between them; a scene without a pushing cell
// returns at once), field (every face).
template <class T>
cudaError_t pressure_cuda(const T* faces, const T* rho0, const T* dt, T* phi_a, T* phi_b, T* field, T* entries,
                          int32_t* cells, int32_t* counters, int64_t B, int64_t r, double h, int64_t iterations,
                          double omega, double stiffness, double pic, cudaStream_t stream);

// x', v' (B, P, 3) by G2P of field (B, 3, F); free (N,) bool (particle p free when free[p % N]).
template <class T>
cudaError_t g2p_cuda(const T* x, const T* v, const T* field, const T* frame, const T* origin, const bool* free,
                     int64_t N, const T* dt, T* xo, T* vo, int64_t B, int64_t P, int64_t r, double h, double pic,
                     cudaStream_t stream);

#define AMS_GRID_DECLARE(T)                                                                                        \
  extern template cudaError_t p2g_cuda<T>(const T*, const T*, const T*, const T*, const T*, T*, int64_t, int64_t, \
                                          int64_t, double, cudaStream_t);                                         \
  extern template cudaError_t pressure_cuda<T>(const T*, const T*, const T*, T*, T*, T*, T*, int32_t*, int32_t*,  \
                                               int64_t, int64_t, double, int64_t, double, double, double,         \
                                               cudaStream_t);                                                     \
  extern template cudaError_t g2p_cuda<T>(const T*, const T*, const T*, const T*, const T*, const bool*, int64_t, \
                                          const T*, T*, T*, int64_t, int64_t, int64_t, double, double, cudaStream_t);
AMS_GRID_DECLARE(float)
AMS_GRID_DECLARE(double)
#undef AMS_GRID_DECLARE

} // extern "C++"

} // namespace grid
} // namespace ams_torch
