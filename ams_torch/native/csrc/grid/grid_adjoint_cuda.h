// Launchers of the CUDA adjoints of the block-sparse hair–hair grid (grid_adjoint.h; the CPU kernels
// in grid_adjoint_cpu.cpp, the shapes there). Plain pointers and a cudaStream_t, no torch headers:
// grid_adjoint_cuda.cu compiles with nvcc alone; grid_adjoint_cuda_binding.cpp (built only against a
// CUDA torch) calls them on the current stream with workspace from torch's allocator. Asynchronous,
// no host synchronisation (count, target and dt are read on the device).
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

namespace ams_torch {
namespace grid {

extern "C++" {

// g_xl, g_vl (B, P, 3), g_m (B, P) from the adjoint g_faces (B, K, 3, 64, 2) of P2G's pool: one
// thread per particle, a gather (no atomics).
template <class T>
cudaError_t p2g_adjoint_cuda(const T* xl, const T* vl, const T* m, const T* origin, const int32_t* table,
                             const T* g_faces, T* g_xl, T* g_vl, T* g_m, int64_t B, int64_t P, int64_t r, int64_t K,
                             double h, cudaStream_t stream);

// g_xl, g_vl (B, P, 3), g_field (B, K, 3, 64; zeroed here, then atomicAdd: the sums' order, hence the
// last bits, vary between runs) and dv (B, P, 3), the forward's head-frame change, from g_dv.
template <class T>
cudaError_t g2p_adjoint_cuda(const T* xl, const T* vl, const T* field, const int32_t* table, const T* origin,
                             const T* g_dv, T* g_xl, T* g_vl, T* g_field, T* dv, int64_t B, int64_t P, int64_t r,
                             int64_t K, double h, double pic, cudaStream_t stream);

// Workspace elements of pressure_adjoint_cuda: of T, and of int32.
int64_t pressure_adjoint_workspace(int64_t B, int64_t K, int64_t iterations, bool ints);

// g_faces (B, K, 3, 64, 2; zeroed here) from g_field (B, K, 3, 64): the pressure recomputed on the
// pool (every cell of the used slots; φ before each sweep kept), then in reverse the face field,
// the sweeps (a launch per sweep and a gather launch: no atomics) and the cell terms, and each face
// gathers its adjoint.
template <class T>
cudaError_t pressure_adjoint_cuda(const T* faces, const int32_t* table, const int32_t* blocks, const int32_t* count,
                                  const T* rho0, const T* dt, const T* g_field, T* g_faces, T* work, int32_t* iwork,
                                  int64_t B, int64_t r, int64_t K, double h, int64_t iterations, double omega,
                                  double stiffness, double pic, cudaStream_t stream);

#define AMS_GRID_ADJOINT_DECLARE(T)                                                                               \
  extern template cudaError_t p2g_adjoint_cuda<T>(const T*, const T*, const T*, const T*, const int32_t*,        \
                                                  const T*, T*, T*, T*, int64_t, int64_t, int64_t, int64_t,       \
                                                  double, cudaStream_t);                                          \
  extern template cudaError_t g2p_adjoint_cuda<T>(const T*, const T*, const T*, const int32_t*, const T*,        \
                                                  const T*, T*, T*, T*, T*, int64_t, int64_t, int64_t, int64_t,   \
                                                  double, double, cudaStream_t);                                  \
  extern template cudaError_t pressure_adjoint_cuda<T>(const T*, const int32_t*, const int32_t*, const int32_t*, \
                                                       const T*, const T*, const T*, T*, T*, int32_t*, int64_t,   \
                                                       int64_t, int64_t, double, int64_t, double, double, double, \
                                                       cudaStream_t);
AMS_GRID_ADJOINT_DECLARE(float)
AMS_GRID_ADJOINT_DECLARE(double)
#undef AMS_GRID_ADJOINT_DECLARE

} // extern "C++"

} // namespace grid
} // namespace ams_torch
