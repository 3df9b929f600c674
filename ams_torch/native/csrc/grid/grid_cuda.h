// Launchers of the CUDA block-sparse hair–hair grid kernels. Plain pointers and a cudaStream_t, no
// torch headers: grid_cuda.cu compiles with nvcc alone, and the thin torch binding
// (grid_cuda_binding.cpp, built only against a CUDA torch) calls these on the current stream.
// Every launcher is asynchronous (no host synchronisation: capturable by CUDA graphs) and
// returns cudaGetLastError() after its last launch. Shapes and layouts: grid.h (K slots per
// scene, nb = R/4 + 1 blocks per axis, 64 cells per block).
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

namespace ams_torch {
namespace grid {

extern "C++" {

// P2G of x, v (B, P, 3), m (B, P) with frame (B, 6, 3), origin (3,) into the block pool: table
// (B, nb^3), blocks (B, K), count (B,) int32 and faces (B, K, 3, 64, 2), all written here
// (faces zeroed first). Workspace: mark, B nb^3 bytes (any content).
template <class T>
cudaError_t p2g_cuda(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int32_t* table,
                     int32_t* blocks, int32_t* count, uint8_t* mark, int64_t B, int64_t P, int64_t r, int64_t K,
                     double h, cudaStream_t stream);

// phi (B, K, 64) and field (B, K, 3, 64) from the pool of P2G; rho0 and dt are device scalars.
// Workspace (any content): entries B K 64 8 values of T, nbr B K 6 int32, pushes B int32. phi_a
// and phi_b (B K 64 each) are zeroed here on the used slots; the result is in phi_a when
// `iterations` is even, else in phi_b. Slots a scene does not use are left unwritten. overflow
// (B,): count > K, or (with sweeps) more active cells than active_capacity; workspace active (B,)
// int32 counts them.
template <class T>
cudaError_t pressure_cuda(const T* faces, const int32_t* table, const int32_t* blocks, const int32_t* count,
                          const T* rho0, const T* dt, T* phi_a, T* phi_b, T* field, bool* overflow, T* entries,
                          int32_t* nbr, int32_t* pushes, int32_t* active, int64_t B, int64_t r, int64_t K, double h,
                          int64_t iterations, double omega, double stiffness, double pic, int64_t active_capacity,
                          cudaStream_t stream);

// x', v' (B, P, 3) by G2P of field (B, K, 3, 64) through table (B, nb^3); free (N,) bool
// (particle p free when free[p % N]).
template <class T>
cudaError_t g2p_cuda(const T* x, const T* v, const T* field, const int32_t* table, const T* frame, const T* origin,
                     const bool* free, int64_t N, const T* dt, T* xo, T* vo, int64_t B, int64_t P, int64_t r,
                     int64_t K, double h, double pic, cudaStream_t stream);

#define AMS_GRID_DECLARE(T)                                                                                        \
  extern template cudaError_t p2g_cuda<T>(const T*, const T*, const T*, const T*, const T*, T*, int32_t*,         \
                                          int32_t*, int32_t*, uint8_t*, int64_t, int64_t, int64_t, int64_t,        \
                                          double, cudaStream_t);                                                   \
  extern template cudaError_t pressure_cuda<T>(const T*, const int32_t*, const int32_t*, const int32_t*,          \
                                               const T*, const T*, T*, T*, T*, bool*, T*, int32_t*, int32_t*,      \
                                               int32_t*, int64_t, int64_t, int64_t, double, int64_t, double,       \
                                               double, double, int64_t, cudaStream_t);                             \
  extern template cudaError_t g2p_cuda<T>(const T*, const T*, const T*, const int32_t*, const T*, const T*,       \
                                          const bool*, int64_t, const T*, T*, T*, int64_t, int64_t, int64_t,       \
                                          int64_t, double, double, cudaStream_t);
AMS_GRID_DECLARE(float)
AMS_GRID_DECLARE(double)
#undef AMS_GRID_DECLARE

} // extern "C++"

} // namespace grid
} // namespace ams_torch
