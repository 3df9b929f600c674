// CUDA kernels of the hair–hair grid's adjoints: the arithmetic of grid_adjoint.h (shared with the
// CPU kernels, grid_adjoint_cpu.cpp), launched by the functions of grid_adjoint_cuda.h. No torch
// headers. Launch sizes follow the capacity K (a static shape); kernels return at once for the slots
// a scene does not use (count read on the device).
//
//   P2G adjoint: one thread per particle, a gather.
//   G2P adjoint: one thread per particle, atomicAdd into the field's adjoint.
//   pressure adjoint: on every cell of the used slots (the CPU kernel lists the active cells; the
//     values are the same): the entries, the sweeps keeping φ before each ((iterations + 1) pool
//     φ's), then φ̄ from the face field, per sweep in reverse a launch per cell (the cell's own
//     part) and a gather launch (each cell sums what its six neighbours' updates owe it: the
//     neighbour relation is symmetric, so no atomics), the cell terms' adjoint (12 face adjoints
//     per active cell), and each face of the used slots gathers its adjoint.
#include <cuda_runtime.h>

#include <stdint.h>

#include "common/launch_cuda.cuh"
#include "grid/grid.h"
#include "grid/grid_adjoint.h"
#include "grid/grid_adjoint_cuda.h"

namespace ams_torch {
namespace grid {
namespace {

constexpr int kThreads = 256;

unsigned blocks_for(int64_t n) { return cuda::grid_stride_blocks(n, kThreads); }

__device__ __forceinline__ int64_t slots_used(const int32_t* count, int64_t b, int64_t K) {
  const int64_t n = count[b];
  return n < 0 ? 0 : (n < K ? n : K);
}

#define AMS_GRID_STRIDE(i, n) \
  for (int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; i < (n); i += int64_t(gridDim.x) * blockDim.x)

template <class T>
__global__ void p2g_adjoint_kernel(const T* xl, const T* vl, const T* m, const T* origin, const int32_t* table,
                                   const T* g_faces, T* g_xl, T* g_vl, T* g_m, int64_t B, int64_t P, int64_t r,
                                   int64_t K, T h) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  AMS_GRID_STRIDE(q, B * P) {
    const int64_t b = q / P;
    p2g_particle_adjoint(xl + 3 * q, vl + 3 * q, m[q], origin, h, r, nb, table + b * nb3,
                         g_faces + b * K * 3 * kBlockCells * 2, g_xl + 3 * q, g_vl + 3 * q, g_m + q);
  }
}

template <class T>
__global__ void g2p_adjoint_kernel(const T* xl, const T* vl, const T* field, const int32_t* table, const T* origin,
                                   const T* g_dv, T* g_xl, T* g_vl, T* g_field, T* dv, int64_t B, int64_t P,
                                   int64_t r, int64_t K, T h, T pic) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  AMS_GRID_STRIDE(q, B * P) {
    const int64_t b = q / P;
    const T* fb = field + b * K * 3 * kBlockCells;
    T* gf = g_field + b * K * 3 * kBlockCells;
    g2p_particle_adjoint(xl + 3 * q, vl + 3 * q, fb, origin, h, r, nb, table + b * nb3, pic, g_dv + 3 * q,
                         g_xl + 3 * q, g_vl + 3 * q, dv + 3 * q,
                         [gf](int32_t f, T value) { atomicAdd(gf + f, value); });
  }
}

// per used slot: its six neighbour slots
__global__ void adj_neighbours_kernel(const int32_t* table, const int32_t* blocks, const int32_t* count, int32_t* nbr,
                                      int64_t B, int64_t r, int64_t K) {
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  AMS_GRID_STRIDE(g, B * K) {
    const int64_t b = g / K;
    if (g % K >= slots_used(count, b, K)) continue;
    slot_neighbours(blocks[g], nb, table + b * nb3, nbr + 6 * g);
  }
}

// per cell of the pool: its entry (zero where not active), its active flag, phi_0 = 0
template <class T>
__global__ void adj_setup_kernel(const T* faces, const int32_t* count, const int32_t* nbr, const T* rho0, const T* dt,
                                 T* entries, int32_t* active, T* phi0, int64_t B, int64_t K, double h, double omega,
                                 double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  AMS_GRID_STRIDE(g, B * K * kBlockCells) {
    const int64_t cell = g / kBlockCells, b = cell / K, slot = cell % K;
    phi0[g] = T(0);
    T* e = entries + kEntry * g;
    const bool on = slot < slots_used(count, b, K) &&
                    cell_entry(faces + b * K * 3 * kBlockCells * 2, slot, int(g % kBlockCells), nbr + 6 * cell, q, e);
    active[g] = on ? 1 : 0;
    if (!on)
      for (int s = 0; s < kEntry; ++s) e[s] = T(0);
  }
}

template <class T>
__global__ void adj_sweep_kernel(const T* entries, const int32_t* nbr, const int32_t* active, const T* src, T* dst,
                                 int64_t B, int64_t K, T keep) {
  AMS_GRID_STRIDE(g, B * K * kBlockCells) {
    const int64_t cell = g / kBlockCells, b = cell / K, slot = cell % K;
    dst[g] = active[g] ? sweep_cell(src + b * K * kBlockCells, slot, int(g % kBlockCells), nbr + 6 * cell,
                                    entries + kEntry * g, keep)
                       : T(0);
  }
}

// φ̄ of each active cell from the face field's adjoint (its lower c-faces: φ_hi; upper: φ_lo)
template <class T>
__global__ void adj_seed_kernel(const T* faces, const int32_t* nbr, const int32_t* active, const T* g_field,
                                const T* rho0, const T* dt, T* g, int64_t B, int64_t K, double h, double omega,
                                double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  AMS_GRID_STRIDE(gi, B * K * kBlockCells) {
    const int64_t cell = gi / kBlockCells, b = cell / K, slot = cell % K;
    const int l = int(gi % kBlockCells);
    T acc = T(0);
    if (active[gi]) {
      const T* fs = faces + b * K * 3 * kBlockCells * 2;
      const T* gfs = g_field + b * K * 3 * kBlockCells;
      for (int c = 0; c < 3; ++c) {
        acc = acc + face_phi_adjoint(fs, gfs, slot, c, l, q);
        int64_t up_slot;
        const int up = neighbour_cell(l, 2 * c + 1, slot, nbr + 6 * cell, &up_slot);
        if (up_slot >= 0) acc = acc - face_phi_adjoint(fs, gfs, up_slot, c, up, q);
      }
    }
    g[gi] = acc;
  }
}

// one sweep's adjoint, the cell's own part: a = g where the update's input >= 0; the adjoints of
// src, coef and the six weights; t = coef a (what the neighbours' φ owe) and a (kept)
template <class T>
__global__ void adj_cell_kernel(const T* entries, const int32_t* nbr, const int32_t* active, const T* phi, const T* g,
                                T* g_entries, T* t, T* a_out, int64_t B, int64_t K, T keep) {
  AMS_GRID_STRIDE(gi, B * K * kBlockCells) {
    if (!active[gi]) {
      t[gi] = T(0);
      a_out[gi] = T(0);
      continue;
    }
    const int64_t cell = gi / kBlockCells, b = cell / K, slot = cell % K;
    const int l = int(gi % kBlockCells);
    const T* ps = phi + b * K * kBlockCells;
    const T* e = entries + kEntry * gi;
    T near[6];
    for (int d = 0; d < 6; ++d) {
      int64_t s;
      const int nl = neighbour_cell(l, d, slot, nbr + 6 * cell, &s);
      near[d] = s < 0 ? T(0) : ps[s * kBlockCells + nl];
    }
    T n = e[2] * near[0];
    for (int d = 1; d < 6; ++d) n = n + e[2 + d] * near[d];
    T pre = e[0] + e[1] * n;
    pre = pre + keep * ps[slot * kBlockCells + l];
    const T a = pre >= T(0) ? g[gi] : T(0);
    T* ge = g_entries + kEntry * gi;
    ge[0] += a;
    ge[1] += a * n;
    const T ti = e[1] * a;
    for (int d = 0; d < 6; ++d) ge[2 + d] += ti * near[d];
    t[gi] = ti;
    a_out[gi] = a;
  }
}

// the adjoint of the sweep's input φ: keep a, plus each neighbour Y's t_Y times the weight Y gives
// this cell (Y = nb_d(X) reads X as its neighbour in direction d ^ 1)
template <class T>
__global__ void adj_gather_kernel(const T* entries, const int32_t* nbr, const int32_t* active, const T* t,
                                  const T* a, T* g_next, int64_t B, int64_t K, T keep) {
  AMS_GRID_STRIDE(gi, B * K * kBlockCells) {
    if (!active[gi]) {
      g_next[gi] = T(0);
      continue;
    }
    const int64_t cell = gi / kBlockCells, b = cell / K, slot = cell % K;
    const int l = int(gi % kBlockCells);
    T acc = keep * a[gi];
    for (int d = 0; d < 6; ++d) {
      int64_t s;
      const int nl = neighbour_cell(l, d, slot, nbr + 6 * cell, &s);
      if (s < 0) continue;
      const int64_t y = (b * K + s) * kBlockCells + nl;
      acc = acc + t[y] * entries[kEntry * y + 2 + (d ^ 1)];
    }
    g_next[gi] = acc;
  }
}

template <class T>
__global__ void adj_entry_kernel(const T* faces, const int32_t* nbr, const int32_t* active, const T* g_entries,
                                 const T* rho0, const T* dt, T* cell_g, int64_t B, int64_t K, double h, double omega,
                                 double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  AMS_GRID_STRIDE(gi, B * K * kBlockCells) {
    if (!active[gi]) continue;
    const int64_t cell = gi / kBlockCells, b = cell / K, slot = cell % K;
    T mass[6], mom[6];
    cell_faces(faces + b * K * 3 * kBlockCells * 2, slot, int(gi % kBlockCells), nbr + 6 * cell, mass, mom);
    const T* ge = g_entries + kEntry * gi;
    cell_entry_adjoint(mass, mom, q, ge[0], ge[1], ge + 2, cell_g + 12 * gi, cell_g + 12 * gi + 6);
  }
}

template <class T>
__global__ void adj_faces_kernel(const T* faces, const int32_t* count, const int32_t* nbr, const int32_t* active,
                                 const T* phi, const T* cell_g, const T* g_field, const T* rho0, const T* dt,
                                 T* g_faces, int64_t B, int64_t K, double h, double omega, double stiffness,
                                 double pic) {
  const PressureConsts<T> q = pressure_consts<T>(h, *rho0, *dt, omega, stiffness, pic);
  AMS_GRID_STRIDE(f, B * K * 3 * kBlockCells) {
    const int64_t cell = f / (3 * kBlockCells), b = cell / K, slot = cell % K;
    if (slot >= slots_used(count, b, K)) continue; // zeroed
    const int c = int((f / kBlockCells) % 3), l = int(f % kBlockCells);
    const T* fs = faces + b * K * 3 * kBlockCells * 2;
    T gm, gp;
    face_field_adjoint(fs, phi + b * K * kBlockCells, slot, c, l, nbr + 6 * cell, q, g_field[f], &gm, &gp);
    const int64_t own = cell * kBlockCells + l;
    if (active[own]) {
      gm = gm + cell_g[12 * own + 2 * c];
      gp = gp + cell_g[12 * own + 6 + 2 * c];
    }
    int64_t lo_slot;
    const int lo = neighbour_cell(l, 2 * c, slot, nbr + 6 * cell, &lo_slot);
    if (lo_slot >= 0) {
      const int64_t below = (b * K + lo_slot) * kBlockCells + lo;
      if (active[below]) {
        gm = gm + cell_g[12 * below + 2 * c + 1];
        gp = gp + cell_g[12 * below + 6 + 2 * c + 1];
      }
    }
    g_faces[2 * f] = gm;
    g_faces[2 * f + 1] = gp;
  }
}

} // namespace

template <class T>
cudaError_t p2g_adjoint_cuda(const T* xl, const T* vl, const T* m, const T* origin, const int32_t* table,
                             const T* g_faces, T* g_xl, T* g_vl, T* g_m, int64_t B, int64_t P, int64_t r, int64_t K,
                             double h, cudaStream_t stream) {
  if (B * P == 0) return cudaSuccess;
  p2g_adjoint_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(xl, vl, m, origin, table, g_faces, g_xl, g_vl,
                                                                    g_m, B, P, r, K, T(h));
  return cudaGetLastError();
}

template <class T>
cudaError_t g2p_adjoint_cuda(const T* xl, const T* vl, const T* field, const int32_t* table, const T* origin,
                             const T* g_dv, T* g_xl, T* g_vl, T* g_field, T* dv, int64_t B, int64_t P, int64_t r,
                             int64_t K, double h, double pic, cudaStream_t stream) {
  cudaError_t err = cudaMemsetAsync(g_field, 0, sizeof(T) * size_t(B * K * 3 * kBlockCells), stream);
  if (err != cudaSuccess || B * P == 0) return err;
  g2p_adjoint_kernel<T><<<blocks_for(B * P), kThreads, 0, stream>>>(xl, vl, field, table, origin, g_dv, g_xl, g_vl,
                                                                    g_field, dv, B, P, r, K, T(h), T(pic));
  return cudaGetLastError();
}

// T workspace: phi history (iterations + 1) n, entries 8 n, their adjoints 8 n, cell_g 12 n, t, a,
// g, g_next: 4 n (n = B K 64). int32: active n, nbr 6 B K.
int64_t pressure_adjoint_workspace(int64_t B, int64_t K, int64_t iterations, bool ints) {
  const int64_t n = B * K * kBlockCells;
  return ints ? n + 6 * B * K : (iterations + 1) * n + (kEntry * 2 + 12 + 4) * n;
}

template <class T>
cudaError_t pressure_adjoint_cuda(const T* faces, const int32_t* table, const int32_t* blocks, const int32_t* count,
                                  const T* rho0, const T* dt, const T* g_field, T* g_faces, T* work, int32_t* iwork,
                                  int64_t B, int64_t r, int64_t K, double h, int64_t iterations, double omega,
                                  double stiffness, double pic, cudaStream_t stream) {
  const int64_t n = B * K * kBlockCells;
  cudaError_t err = cudaMemsetAsync(g_faces, 0, sizeof(T) * size_t(2 * 3 * n), stream);
  if (err != cudaSuccess || n == 0) return err;
  T* phi = work; // (iterations + 1) n: φ before each sweep, then the last
  T* entries = phi + (iterations + 1) * n;
  T* g_entries = entries + kEntry * n;
  T* cell_g = g_entries + kEntry * n;
  T* t = cell_g + 12 * n;
  T* a = t + n;
  T* g = a + n;
  T* g_next = g + n;
  int32_t* active = iwork;
  int32_t* nbr = active + n;
  err = cudaMemsetAsync(g_entries, 0, sizeof(T) * size_t(kEntry * n), stream);
  if (err != cudaSuccess) return err;
  const T keep = T(1.0 - omega);
  const unsigned cells = blocks_for(n);
  adj_neighbours_kernel<<<blocks_for(B * K), kThreads, 0, stream>>>(table, blocks, count, nbr, B, r, K);
  adj_setup_kernel<T><<<cells, kThreads, 0, stream>>>(faces, count, nbr, rho0, dt, entries, active, phi, B, K, h, omega,
                                                      stiffness, pic);
  if (iterations > 0) {
    for (int64_t k = 0; k < iterations; ++k)
      adj_sweep_kernel<T><<<cells, kThreads, 0, stream>>>(entries, nbr, active, phi + k * n, phi + (k + 1) * n, B, K,
                                                          keep);
    adj_seed_kernel<T><<<cells, kThreads, 0, stream>>>(faces, nbr, active, g_field, rho0, dt, g, B, K, h, omega,
                                                       stiffness, pic);
    for (int64_t k = iterations - 1; k >= 0; --k) {
      adj_cell_kernel<T><<<cells, kThreads, 0, stream>>>(entries, nbr, active, phi + k * n, g, g_entries, t, a, B, K,
                                                         keep);
      adj_gather_kernel<T><<<cells, kThreads, 0, stream>>>(entries, nbr, active, t, a, g_next, B, K, keep);
      T* tmp = g;
      g = g_next;
      g_next = tmp;
    }
    adj_entry_kernel<T><<<cells, kThreads, 0, stream>>>(faces, nbr, active, g_entries, rho0, dt, cell_g, B, K, h,
                                                        omega, stiffness, pic);
  }
  adj_faces_kernel<T><<<blocks_for(3 * n), kThreads, 0, stream>>>(faces, count, nbr, active, phi + iterations * n,
                                                                  cell_g, g_field, rho0, dt, g_faces, B, K, h, omega,
                                                                  stiffness, pic);
  return cudaGetLastError();
}

#define AMS_GRID_ADJOINT_INSTANTIATE(T)                                                                          \
  template cudaError_t p2g_adjoint_cuda<T>(const T*, const T*, const T*, const T*, const int32_t*, const T*, T*, \
                                           T*, T*, int64_t, int64_t, int64_t, int64_t, double, cudaStream_t);    \
  template cudaError_t g2p_adjoint_cuda<T>(const T*, const T*, const T*, const int32_t*, const T*, const T*, T*, \
                                           T*, T*, T*, int64_t, int64_t, int64_t, int64_t, double, double,       \
                                           cudaStream_t);                                                        \
  template cudaError_t pressure_adjoint_cuda<T>(const T*, const int32_t*, const int32_t*, const int32_t*,        \
                                                const T*, const T*, const T*, T*, T*, int32_t*, int64_t, int64_t, \
                                                int64_t, double, int64_t, double, double, double, cudaStream_t);
AMS_GRID_ADJOINT_INSTANTIATE(float)
AMS_GRID_ADJOINT_INSTANTIATE(double)
#undef AMS_GRID_ADJOINT_INSTANTIATE

} // namespace grid
} // namespace ams_torch
