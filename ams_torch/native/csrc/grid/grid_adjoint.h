// Adjoints (vector-Jacobian products) of the block-sparse hair–hair grid's arithmetic (grid.h),
// written once for the host (grid_adjoint_cpu.cpp) and the device. The definition is the torch
// code of ams_torch/stages/hair_hair/sparse.py differentiated by autograd; every function below
// is that derivative written out, with autograd's conventions where the definition is not smooth:
//   * floor() has derivative 0, so a 1-D weight's slope in its coordinate is -1, +1 or 0
//     (transfer.face_corner_rows: w0 = 1 - f or f or 0, w1 = f or 1 - f or 0 by the corner's case);
//   * torch.where passes the gradient to the branch it took; maximum(a, b) passes it to the larger,
//     half to each on a tie; clamp_min(0) passes it where its input is >= 0 (sweeps.h).
// The P2G and G2P adjoints work in the head frame (xl, vl: the head-frame position and relative
// velocity); the change of frame (transfer.to_head, transfer.apply_change) is differentiated by
// autograd on its torch definition by the caller (a few elementwise operations per particle).
// No torch headers.
#pragma once

#include <math.h>
#include <stdint.h>

#include "grid/grid.h"

namespace ams_torch {
namespace grid {

// Slopes dw/dg of the two weights of axis_stencil(g, n, r, w): (-1, +1) inside, (+1, 0) half below,
// (0, -1) half above, (0, 0) fully outside.
template <class T>
AMS_GRID_HD void axis_stencil_slope(T g, int64_t n, int64_t r, T* dw) {
  const int64_t i0 = clamped_floor(g, r);
  const int64_t b = i0 < 0 ? 0 : (i0 > n - 2 ? n - 2 : i0);
  const int64_t d = i0 - b;
  dw[0] = d == 0 ? T(-1) : (d == -1 ? T(1) : T(0));
  dw[1] = d == 0 ? T(1) : (d == 1 ? T(-1) : T(0));
}

// The slopes of a particle's 1-D weights, as ParticleStencil's weights: [variant][axis][corner].
template <class T>
AMS_GRID_HD void particle_slopes(const T* xl, const T* origin, T h, int64_t r, T dw[2][3][2]) {
  for (int a = 0; a < 3; ++a) {
    const T g = cell_coord(xl, origin, h, a);
    axis_stencil_slope(g, r + 1, r, dw[0][a]);
    axis_stencil_slope(g - T(0.5), r, r, dw[1][a]);
  }
}

// Adjoint of component C's trilinear weights w[4i + 2j + k] = (wx_i wy_j) wz_k: given gw[8] (the
// adjoint of each corner weight), accumulates the adjoints of the 1-D weights into g1[variant][axis][corner].
template <int C, class T>
AMS_GRID_HD void corner_weights_adjoint(const ParticleStencil<T>& s, const T* gw, T g1[2][3][2]) {
  constexpr int v0 = C == 0 ? 0 : 1, v1 = C == 1 ? 0 : 1, v2 = C == 2 ? 0 : 1;
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j) {
      const T w01 = s.w[v0][0][i] * s.w[v1][1][j];
      T g01 = T(0);
      for (int k = 0; k < 2; ++k) {
        const T gk = gw[4 * i + 2 * j + k];
        g01 = g01 + gk * s.w[v2][2][k];
        g1[v2][2][k] = g1[v2][2][k] + gk * w01;
      }
      g1[v0][0][i] = g1[v0][0][i] + g01 * s.w[v1][1][j];
      g1[v1][1][j] = g1[v1][1][j] + g01 * s.w[v0][0][i];
    }
}

// g_xl[a] from the adjoints of the 1-D weights: g = (xl - origin) / h, f = g - floor(g).
template <class T>
AMS_GRID_HD void stencil_position_adjoint(const T* xl, const T* origin, T h, int64_t r, const T g1[2][3][2],
                                          T* g_xl) {
  T dw[2][3][2];
  particle_slopes(xl, origin, h, r, dw);
  for (int a = 0; a < 3; ++a) {
    const T gg = (dw[0][a][0] * g1[0][a][0] + dw[0][a][1] * g1[0][a][1]) +
                 (dw[1][a][0] * g1[1][a][0] + dw[1][a][1] * g1[1][a][1]);
    g_xl[a] = gg / h;
  }
}

// The component-C corners of a particle (grid.h's corner_faces), by a runtime C.
template <class T>
AMS_GRID_HD void corner_faces_rt(int c, const ParticleStencil<T>& s, const PoolCorners& pc, int32_t* face, T* w) {
  if (c == 0)
    corner_faces<0>(s, pc, face, w);
  else if (c == 1)
    corner_faces<1>(s, pc, face, w);
  else
    corner_faces<2>(s, pc, face, w);
}

template <class T>
AMS_GRID_HD void corner_weights_adjoint_rt(int c, const ParticleStencil<T>& s, const T* gw, T g1[2][3][2]) {
  if (c == 0)
    corner_weights_adjoint<0>(s, gw, g1);
  else if (c == 1)
    corner_weights_adjoint<1>(s, gw, g1);
  else
    corner_weights_adjoint<2>(s, gw, g1);
}

// Adjoint of P2G for one particle (p2g_particle: faces[f] += (w m, w m vl_c)): given the adjoint
// g_faces of one scene's pool faces (mass, momentum pairs), writes g_xl[3], g_vl[3] and *g_m. A
// gather: no two particles write the same value.
template <class T>
AMS_GRID_HD void p2g_particle_adjoint(const T* xl, const T* vl, T m, const T* origin, T h, int64_t r, int64_t nb,
                                      const int32_t* table, const T* g_faces, T* g_xl, T* g_vl, T* g_m) {
  ParticleStencil<T> s;
  particle_stencil(xl, origin, h, r, s);
  PoolCorners pc;
  pool_corners(s, nb, table, pc);
  T g1[2][3][2] = {{{T(0), T(0)}, {T(0), T(0)}, {T(0), T(0)}}, {{T(0), T(0)}, {T(0), T(0)}, {T(0), T(0)}}};
  T gm = T(0);
  for (int c = 0; c < 3; ++c) {
    int32_t face[8];
    T w[8], gw[8];
    corner_faces_rt(c, s, pc, face, w);
    T gmom = T(0);
    for (int k = 0; k < 8; ++k) {
      const T gmass = face[k] < 0 ? T(0) : g_faces[2 * face[k]];
      const T gp = face[k] < 0 ? T(0) : g_faces[2 * face[k] + 1];
      // value pair (w m, w (m vl_c)): d/dw = m gmass + (m vl_c) gp
      const T mv = m * vl[c];
      gw[k] = m * gmass + mv * gp;
      gm = gm + w[k] * gmass;
      gmom = gmom + w[k] * gp; // adjoint of m vl_c
    }
    gm = gm + gmom * vl[c];
    g_vl[c] = gmom * m;
    corner_weights_adjoint_rt(c, s, gw, g1);
  }
  *g_m = gm;
  stencil_position_adjoint(xl, origin, h, r, g1, g_xl);
}

// Adjoint of the G2P change for one particle: dv_c = sum_k field[f_k] w_k - pic (sum_k w_k) vl_c
// (transfer.interpolate_change), given g_dv[3] (the adjoint of the head-frame change, zero for a
// pinned particle). Writes g_xl[3], g_vl[3] and dv[3] (the change itself, as grid.h's g2p_particle
// computes it: the caller differentiates the rotation back to the world with it); calls
// scatter(face, value) for each corner's field[face] += value (corners without a slot skipped).
template <class T, class Scatter>
AMS_GRID_HD void g2p_particle_adjoint(const T* xl, const T* vl, const T* field, const T* origin, T h, int64_t r,
                                      int64_t nb, const int32_t* table, T pic, const T* g_dv, T* g_xl, T* g_vl,
                                      T* dv, Scatter scatter) {
  ParticleStencil<T> s;
  particle_stencil(xl, origin, h, r, s);
  PoolCorners pc;
  pool_corners(s, nb, table, pc);
  T g1[2][3][2] = {{{T(0), T(0)}, {T(0), T(0)}, {T(0), T(0)}}, {{T(0), T(0)}, {T(0), T(0)}, {T(0), T(0)}}};
  for (int c = 0; c < 3; ++c) {
    int32_t face[8];
    T w[8], gw[8];
    corner_faces_rt(c, s, pc, face, w);
    const T g = g_dv[c];
    T ws = T(0), acc = T(0);
    for (int k = 0; k < 8; ++k) {
      const T fv = face[k] < 0 ? T(0) : field[face[k]];
      if (face[k] >= 0) acc = acc + fv * w[k];
      gw[k] = g * fv - pic * g * vl[c];
      ws = ws + w[k];
      if (face[k] >= 0) scatter(face[k], g * w[k]);
    }
    dv[c] = acc - pic * ws * vl[c];
    g_vl[c] = -(pic * ws) * g;
    corner_weights_adjoint_rt(c, s, gw, g1);
  }
  stencil_position_adjoint(xl, origin, h, r, g1, g_xl);
}

// The six faces of pool cell (slot, l): mass and momentum of its lower c-face (its own, index 2c)
// and upper c-face (the next cell's along c, index 2c + 1).
template <class T>
AMS_GRID_HD void cell_faces(const T* faces, int64_t slot, int l, const int32_t* nbr, T* mass, T* mom) {
  for (int c = 0; c < 3; ++c) {
    face_values(faces, slot, c, l, &mass[2 * c], &mom[2 * c]);
    int64_t up_slot;
    const int up = neighbour_cell(l, 2 * c + 1, slot, nbr, &up_slot);
    face_values(faces, up_slot, c, up, &mass[2 * c + 1], &mom[2 * c + 1]);
  }
}

// Adjoint of an active cell's entry (grid.h's cell_entry: src, coef, 1/rho_f of the six faces):
// given g_src, g_coef and g_inv[6], writes the adjoints of the six faces' mass and momentum.
template <class T>
AMS_GRID_HD void cell_entry_adjoint(const T* mass, const T* mom, const PressureConsts<T>& q, T g_src, T g_coef,
                                    const T* g_inv, T* g_mass, T* g_mom) {
  T vel[6], inv[6];
  for (int f = 0; f < 6; ++f) {
    vel[f] = mass[f] > T(0) ? mom[f] / mass[f] : T(0);
    inv[f] = q.h3 / mass[f];
  }
  T total = T(0.5) * (mass[0] + mass[1]);
  total = total + T(0.5) * (mass[2] + mass[3]);
  total = total + T(0.5) * (mass[4] + mass[5]);
  const T rho = total / T(3) / q.h3;
  T div = vel[1] - vel[0];
  div = div + (vel[3] - vel[2]);
  div = div + (vel[5] - vel[4]);
  div = div / q.h;
  const T rhs0 = q.stiffness * (T(1) - q.rho0 / rho) / q.dt;
  T rhs = rhs0;
  if (rho > q.rho0) rhs = rhs0 > -div ? rhs0 : -div;
  T diag = inv[0] + inv[1];
  for (int f = 2; f < 6; ++f) diag = diag + inv[f];
  const T coef = q.omega / diag;
  // src = coef (h2 rhs)
  const T gc = g_coef + g_src * (q.h2 * rhs);
  const T g_rhs = g_src * coef * q.h2;
  const T g_diag = -gc * q.omega / (diag * diag);
  T g_rhs0 = g_rhs, g_div = T(0);
  if (rho > q.rho0) {
    const T nd = -div;
    if (rhs0 > nd) {
      g_div = T(0);
    } else if (rhs0 < nd) {
      g_rhs0 = T(0);
      g_div = -g_rhs;
    } else {
      g_rhs0 = g_rhs / T(2);
      g_div = -(g_rhs / T(2));
    }
  }
  const T g_rho = g_rhs0 * q.stiffness / q.dt * q.rho0 / (rho * rho);
  const T g_total = g_rho / T(3) / q.h3;
  const T g_dsum = g_div / q.h;
  for (int f = 0; f < 6; ++f) {
    const T g_vel = (f & 1) ? g_dsum : -g_dsum;
    const T gi = g_inv[f] + g_diag;
    T gmass = T(0.5) * g_total - gi * inv[f] / mass[f];
    T gmom = T(0);
    if (mass[f] > T(0)) {
      gmom = g_vel / mass[f];
      gmass = gmass - g_vel * vel[f] / mass[f];
    }
    g_mass[f] = gmass;
    g_mom[f] = gmom;
  }
}

// Adjoint of face_field for pool face (slot, c, l) given its adjoint g: the face's own mass and
// momentum adjoints (*g_mass, *g_mom). (Its phi terms go to the cells: face_phi_adjoint.)
template <class T>
AMS_GRID_HD void face_field_adjoint(const T* faces, const T* phi, int64_t slot, int c, int l, const int32_t* nbr,
                                    const PressureConsts<T>& q, T g, T* g_mass, T* g_mom) {
  T mf, pf;
  face_values(faces, slot, c, l, &mf, &pf);
  *g_mass = T(0);
  *g_mom = T(0);
  if (!(mf > T(0))) return;
  const T u = pf / mf;
  *g_mom = q.pic * g / mf;
  T gm = -(q.pic * g) * u / mf;
  if (mf > q.eps) {
    const T inv = q.h3 / mf;
    int64_t lo_slot;
    const int lo = neighbour_cell(l, 2 * c, slot, nbr, &lo_slot);
    const T phi_hi = phi[slot * kBlockCells + l];
    const T phi_lo = lo_slot < 0 ? T(0) : phi[lo_slot * kBlockCells + lo];
    const T grad = (phi_hi - phi_lo) / q.h;
    // du = -(grad inv)
    const T g_inv = -g * grad;
    gm = gm - g_inv * inv / mf;
  }
  *g_mass = gm;
}

// The face-field adjoint's φ̄ term of face (slot, c, l): the adjoint of φ_hi (φ_lo gets its negative).
template <class T>
AMS_GRID_HD T face_phi_adjoint(const T* faces, const T* g_field, int64_t slot, int c, int l, const PressureConsts<T>& q) {
  T mf, pf;
  face_values(faces, slot, c, l, &mf, &pf);
  if (!(mf > q.eps)) return T(0);
  const T inv = q.h3 / mf;
  return -g_field[(slot * 3 + c) * kBlockCells + l] * inv / q.h;
}

} // namespace grid
} // namespace ams_torch
