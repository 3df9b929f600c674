// The pressure solve's projected weighted-Jacobi sweeps on the listed active cells, and their
// adjoint, written once for the host (sweeps_cpu.cpp) and the device (sweeps_cuda.cu). The
// definition is ams_torch/stages/hair_hair/sparse.py::_sweeps (forward) and ::_Sweeps.backward
// (its vector-Jacobian product); the same operations in the same order.
//
// Layout: L + 1 list slots (the last a zero that stays zero: src = coef = w = 0 there); src, coef
// (L + 1); w (6, L + 1) the six neighbour weights 1/ρ_f in the order x−, x+, y−, y+, z−, z+;
// nbr (6, L + 1) int64, the neighbours' list slots (L: none). One sweep from φ:
//   n_i = Σ_d w[d][i] φ[nbr[d][i]]  (d = 0 … 5 in order),  φ'_i = max(0, (src_i + coef_i n_i) + keep φ_i)
// with keep = 1 − ω. Its adjoint for the adjoint g of φ' (per slot i; then a scatter):
//   a_i = pre_i >= 0 ? g_i : 0   (clamp_min passes the gradient at 0, as torch's)
//   s̄rc_i += a_i,  c̄oef_i += a_i n_i,  t_i = coef_i a_i,  w̄[d][i] += t_i φ[nbr[d][i]]
//   φ̄_i = keep a_i,  then φ̄[nbr[d][i]] += w[d][i] t_i  (d = 0 … 5, i = 0 … L: index_add's order)
// No torch headers.
#pragma once

#include <stdint.h>

#include "grid/grid.h"

namespace ams_torch {
namespace grid {

constexpr int kSweepDirs = 6;

// n_i of one slot.
template <class T>
AMS_GRID_HD T sweep_neighbours(int64_t i, int64_t n1, const T* w, const int64_t* nbr, const T* phi) {
  T acc = w[i] * phi[nbr[i]];
  for (int d = 1; d < kSweepDirs; ++d) acc = acc + w[d * n1 + i] * phi[nbr[d * n1 + i]];
  return acc;
}

// φ' of one slot.
template <class T>
AMS_GRID_HD T sweep_cell(int64_t i, int64_t n1, const T* src, const T* coef, const T* w, const int64_t* nbr,
                         const T* phi, T keep) {
  const T nxt = src[i] + coef[i] * sweep_neighbours(i, n1, w, nbr, phi);
  const T val = nxt + keep * phi[i];
  return val < T(0) ? T(0) : val; // clamp_min(0) (NaN stays NaN)
}

// The per-slot part of one sweep's adjoint at the sweep's input φ: accumulates s̄rc, c̄oef, w̄,
// writes t_i (the scatter's weights' factor) and φ̄_i = keep a_i.
template <class T>
AMS_GRID_HD void sweep_cell_adjoint(int64_t i, int64_t n1, const T* src, const T* coef, const T* w,
                                    const int64_t* nbr, const T* phi, T keep, const T* g, T* g_src, T* g_coef,
                                    T* g_w, T* t, T* g_phi) {
  T near[kSweepDirs]; // φ of the six neighbours, read once
  for (int d = 0; d < kSweepDirs; ++d) near[d] = phi[nbr[d * n1 + i]];
  T n = w[i] * near[0];
  for (int d = 1; d < kSweepDirs; ++d) n = n + w[d * n1 + i] * near[d]; // sweep_neighbours' order
  const T pre = (src[i] + coef[i] * n) + keep * phi[i];
  const T a = pre >= T(0) ? g[i] : T(0);
  g_src[i] += a;
  g_coef[i] += a * n;
  const T ti = coef[i] * a;
  t[i] = ti;
  g_phi[i] = keep * a;
  for (int d = 0; d < kSweepDirs; ++d) g_w[d * n1 + i] += ti * near[d];
}

} // namespace grid
} // namespace ams_torch
