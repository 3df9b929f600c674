// CUDA kernels of the block-sparse hair–hair grid: the arithmetic of grid.h (shared with the CPU
// kernels), launched by the functions of grid_cuda.h. No torch headers (nvcc alone compiles this
// file). Layouts: grid.h. Launch sizes follow the capacity K (a static shape), and every kernel
// returns at once for the slots a scene does not use (count read on the device: no host sync).
//
//   P2G: mark the blocks each particle's stencils touch (one thread per particle), give every
//        marked block a slot (one thread per block of the grid's nb^3 table, atomicAdd per scene:
//        slots in any order), then one thread per particle, warp-aggregated atomicAdd of mass and
//        momentum into the pool (summation order, hence the last bits, vary between runs; the
//        binding tells torch's deterministic mode: alertNotDeterministic).
//   pressure: the neighbour slots of every used slot; the entries of every used cell (active
//        cells are counted per scene; one with src > 0 marks its scene as pushing); then ONE
//        launch for all Jacobi sweeps: one thread block per scene loops over the cells of its
//        used slots, __syncthreads() between sweeps (double-buffered phi, so the result does not
//        depend on the order); a scene that does not push returns at once (phi stays 0). Then the
//        face field of every used slot.
//   G2P: one thread per particle, fused with the FLIP/PIC blend and the frame changes.
#include <cuda_runtime.h>

#include <stdint.h>

#include "grid/grid.h"
#include "grid/grid_cuda.h"
#include "common/launch_cuda.cuh"
#include "common/warp_atomic_cuda.cuh"

namespace ams_torch {
namespace grid {
namespace {

constexpr int kThreads = 256;      // threads per block of the per-particle / per-cell kernels
constexpr int kSweepThreads = 512; // threads of the one block per scene of the sweeps
constexpr int64_t kMaxBlocks = int64_t(1) << 20;

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

// slots of scene b in use
__device__ __forceinline__ int64_t used_slots(const int32_t* count, int64_t b, int64_t K) {
  const int64_t n = count[b];
  return n < 0 ? 0 : (n < K ? n : K);
}

template <class T>
__global__ void mark_kernel(const T* x, const T* v, const T* frame, const T* origin, uint8_t* mark, int64_t B,
                            int64_t P, int64_t r, T h) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  for (int64_t q = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; q < B * P; q += int64_t(gridDim.x) * blockDim.x) {
    T xl[3], vl[3];
    to_head(frame + 18 * (q / P), x + 3 * q, v + 3 * q, xl, vl);
    int64_t first[3], last[3];
    if (!particle_blocks(xl, origin, h, r, first, last)) continue;
    uint8_t* mk = mark + (q / P) * nb3;
    for (int64_t i = first[0]; i <= last[0]; ++i)
      for (int64_t j = first[1]; j <= last[1]; ++j)
        for (int64_t k = first[2]; k <= last[2]; ++k) mk[(i * nb + j) * nb + k] = 1; // every writer stores 1
  }
}

__global__ void assign_kernel(const uint8_t* mark, int32_t* table, int32_t* blocks, int32_t* count, int64_t B,
                              int64_t nb3, int64_t K) {
  for (int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; g < B * nb3; g += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = g / nb3;
    int32_t slot = -1;
    if (mark[g]) {
      const int64_t s = atomicAdd(count + b, 1);
      if (s < K) {
        slot = int32_t(s);
        blocks[b * K + s] = int32_t(g % nb3);
      }
    }
    table[g] = slot;
  }
}

template <class T>
__global__ void p2g_kernel(const T* x, const T* v, const T* m, const T* frame, const T* origin, const int32_t* table,
                           T* faces, int64_t B, int64_t P, int64_t r, int64_t K, T h) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  for (int64_t q = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; q < B * P; q += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = q / P;
    T xl[3], vl[3];
    to_head(frame + 18 * b, x + 3 * q, v + 3 * q, xl, vl);
    p2g_particle(xl, vl, m[q], origin, h, r, nb, table + b * nb3, faces + b * K * 3 * kBlockCells * 2, AtomicAdd<T>());
  }
}

__global__ void neighbours_kernel(const int32_t* table, const int32_t* blocks, const int32_t* count, int32_t* nbr,
                                  int64_t B, int64_t r, int64_t K) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  for (int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; g < B * K; g += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = g / K;
    if (g % K >= used_slots(count, b, K)) continue;
    slot_neighbours(blocks[g], nb, table + b * nb3, nbr + 6 * g);
  }
}

template <class T>
__global__ void setup_kernel(const T* faces, const int32_t* count, const int32_t* nbr, const T* rho0, const T* dt,
                             T* entries, T* phi_a, T* phi_b, int32_t* pushes, int32_t* active, int64_t B, int64_t K,
                             bool solve, double h, double omega, double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  for (int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; g < B * K * kBlockCells;
       g += int64_t(gridDim.x) * blockDim.x) {
    const int64_t cell = g / kBlockCells; // b K + slot
    const int64_t b = cell / K, slot = cell % K;
    phi_a[g] = T(0); // unused slots too: every output is defined (0 outside the hair)
    phi_b[g] = T(0);
    if (slot >= used_slots(count, b, K) || !solve) continue;
    T* e = entries + kEntry * g;
    if (!cell_entry(faces + b * K * 3 * kBlockCells * 2, slot, int(g % kBlockCells), nbr + 6 * cell, q, e)) {
      for (int s = 0; s < kEntry; ++s) e[s] = T(0); // not active: the sweeps keep its phi at 0
      continue;
    }
    atomicAdd(active + b, 1);
    if (e[0] > T(0)) pushes[b] = 1;
  }
}

template <class T>
__global__ void __launch_bounds__(kSweepThreads) sweep_kernel(const T* entries, const int32_t* nbr,
                                                              const int32_t* count, const int32_t* pushes, T* phi_a,
                                                              T* phi_b, int64_t K, int64_t iterations,
                                                              double one_minus_omega) {
  const int64_t b = blockIdx.x;
  if (pushes[b] == 0) return; // the same for every thread of the block
  const int64_t n = used_slots(count, b, K) * kBlockCells;
  const T keep = T(one_minus_omega);
  T* pa = phi_a + b * K * kBlockCells;
  T* pb = phi_b + b * K * kBlockCells;
  const T* e = entries + kEntry * b * K * kBlockCells;
  const int32_t* nb = nbr + 6 * b * K;
  for (int64_t it = 0; it < iterations; ++it) {
    const T* src = (it & 1) ? pb : pa;
    T* dst = (it & 1) ? pa : pb;
    for (int64_t k = threadIdx.x; k < n; k += blockDim.x) {
      const int64_t slot = k / kBlockCells;
      dst[k] = sweep_cell(src, slot, int(k % kBlockCells), nb + 6 * slot, e + kEntry * k, keep);
    }
    __syncthreads(); // this sweep's writes are visible to the whole block before the next reads them
  }
}

// overflow[b]: the scene's hair occupied more than K blocks, or (with sweeps) had more active
// cells than the torch path's list holds.
__global__ void overflow_kernel(const int32_t* count, const int32_t* active, bool* overflow, int64_t B, int64_t K,
                                int64_t active_capacity) {
  for (int64_t b = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; b < B; b += int64_t(gridDim.x) * blockDim.x)
    overflow[b] = count[b] > K || active[b] > active_capacity;
}

template <class T>
__global__ void field_kernel(const T* faces, const T* phi, const int32_t* count, const int32_t* nbr, const T* rho0,
                             const T* dt, T* field, int64_t B, int64_t K, double h, double omega, double stiffness,
                             double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  for (int64_t f = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; f < B * K * 3 * kBlockCells;
       f += int64_t(gridDim.x) * blockDim.x) {
    const int64_t cell = f / (3 * kBlockCells); // b K + slot
    const int64_t b = cell / K, slot = cell % K;
    if (slot >= used_slots(count, b, K)) {
      field[f] = T(0); // an unused slot: no hair, no velocity
      continue;
    }
    const int c = int((f / kBlockCells) % 3);
    field[f] = face_field(faces + b * K * 3 * kBlockCells * 2, phi + b * K * kBlockCells, slot, c,
                          int(f % kBlockCells), nbr + 6 * cell, q);
  }
}

template <class T>
__global__ void g2p_kernel(const T* x, const T* v, const T* field, const int32_t* table, const T* frame,
                           const T* origin, const bool* free, int64_t N, const T* dt, T* xo, T* vo, int64_t B,
                           int64_t P, int64_t r, int64_t K, T h, T pic) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  const T dtv = *dt;
  for (int64_t q = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; q < B * P; q += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = q / P;
    g2p_particle(frame + 18 * b, x + 3 * q, v + 3 * q, field + b * K * 3 * kBlockCells, table + b * nb3, nb, origin,
                 h, r, pic, free[(q % P) % N], dtv, xo + 3 * q, vo + 3 * q);
  }
}

} // namespace

template <class T>
cudaError_t p2g_cuda(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int32_t* table,
                     int32_t* blocks, int32_t* count, uint8_t* mark, int64_t B, int64_t P, int64_t r, int64_t K,
                     double h, cudaStream_t stream) {
  if (B == 0) return cudaSuccess;
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  cudaError_t err = cudaMemsetAsync(mark, 0, size_t(B * nb3), stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(count, 0, sizeof(int32_t) * size_t(B), stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(blocks, 0xff, sizeof(int32_t) * size_t(B * K), stream); // -1
  if (err == cudaSuccess) err = cudaMemsetAsync(faces, 0, sizeof(T) * size_t(B * K * 3 * kBlockCells * 2), stream);
  if (err != cudaSuccess) return err;
  if (P > 0) mark_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(x, v, frame, origin, mark, B, P, r, T(h));
  assign_kernel<<<blocks_for(B * nb3), kThreads, 0, stream>>>(mark, table, blocks, count, B, nb3, K);
  if (P > 0)
    p2g_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(x, v, m, frame, origin, table, faces, B, P, r, K, T(h));
  return cudaGetLastError();
}

template <class T>
cudaError_t pressure_cuda(const T* faces, const int32_t* table, const int32_t* blocks, const int32_t* count,
                          const T* rho0, const T* dt, T* phi_a, T* phi_b, T* field, bool* overflow, T* entries,
                          int32_t* nbr, int32_t* pushes, int32_t* active, int64_t B, int64_t r, int64_t K, double h,
                          int64_t iterations, double omega, double stiffness, double pic, int64_t active_capacity,
                          cudaStream_t stream) {
  if (B == 0) return cudaSuccess;
  if (B > 0x7fffffffLL) return cudaErrorInvalidValue;
  cudaError_t err = cudaMemsetAsync(pushes, 0, sizeof(int32_t) * size_t(B), stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(active, 0, sizeof(int32_t) * size_t(B), stream);
  if (err != cudaSuccess) return err;
  neighbours_kernel<<<blocks_for(B * K), kThreads, 0, stream>>>(table, blocks, count, nbr, B, r, K);
  setup_kernel<T><<<blocks_for(B * K * kBlockCells), kThreads, 0, stream>>>(
      faces, count, nbr, rho0, dt, entries, phi_a, phi_b, pushes, active, B, K, iterations > 0, h, omega, stiffness,
      pic);
  if (iterations > 0)
    sweep_kernel<T><<<unsigned(B), kSweepThreads, 0, stream>>>(entries, nbr, count, pushes, phi_a, phi_b, K,
                                                              iterations, 1.0 - omega);
  overflow_kernel<<<blocks_for(B), kThreads, 0, stream>>>(count, active, overflow, B, K, active_capacity);
  const T* phi = iterations % 2 == 0 ? phi_a : phi_b;
  field_kernel<T><<<blocks_for(B * K * 3 * kBlockCells), kThreads, 0, stream>>>(faces, phi, count, nbr, rho0, dt,
                                                                                 field, B, K, h, omega, stiffness, pic);
  return cudaGetLastError();
}

template <class T>
cudaError_t g2p_cuda(const T* x, const T* v, const T* field, const int32_t* table, const T* frame, const T* origin,
                     const bool* free, int64_t N, const T* dt, T* xo, T* vo, int64_t B, int64_t P, int64_t r,
                     int64_t K, double h, double pic, cudaStream_t stream) {
  if (B * P == 0) return cudaSuccess;
  g2p_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(x, v, field, table, frame, origin, free, N, dt, xo, vo, B,
                                                            P, r, K, T(h), T(pic));
  return cudaGetLastError();
}

#define AMS_GRID_INSTANTIATE(T)                                                                                    \
  template cudaError_t p2g_cuda<T>(const T*, const T*, const T*, const T*, const T*, T*, int32_t*, int32_t*,       \
                                   int32_t*, uint8_t*, int64_t, int64_t, int64_t, int64_t, double, cudaStream_t);  \
  template cudaError_t pressure_cuda<T>(const T*, const int32_t*, const int32_t*, const int32_t*, const T*,        \
                                        const T*, T*, T*, T*, bool*, T*, int32_t*, int32_t*, int32_t*, int64_t,    \
                                        int64_t, int64_t, double, int64_t, double, double, double, int64_t,        \
                                        cudaStream_t);                                                             \
  template cudaError_t g2p_cuda<T>(const T*, const T*, const T*, const int32_t*, const T*, const T*, const bool*,  \
                                   int64_t, const T*, T*, T*, int64_t, int64_t, int64_t, int64_t, double, double,  \
                                   cudaStream_t);
AMS_GRID_INSTANTIATE(float)
AMS_GRID_INSTANTIATE(double)
#undef AMS_GRID_INSTANTIATE

} // namespace grid
} // namespace ams_torch
