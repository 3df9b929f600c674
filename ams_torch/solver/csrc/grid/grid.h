// The per-particle, per-cell and per-face arithmetic of the hair–hair grid (SPEC §6), written
// once for the host (grid_cpu.cpp) and the device (grid_cuda.cu). The definition is the torch
// code of ams_torch/stages/hair_hair/{transfer,pressure}.py; every function below does the same
// operations in the same order (up to the compiler's fused multiply-adds).
//
// Layouts (all contiguous, one scene's block after another):
//   frame  (B, 6, 3): rows 0-2 the rotation R (world <- head), 3 the translation T (m), 4 the
//          linear velocity V (m/s), 5 the angular velocity W (rad/s, world frame).
//   faces  (B, 3, F, 2), F = (R+1) R R: for component c the face grid of dims n_c (R+1 along
//          axis c, R along the others) row-major; [.., 0] mass (kg), [.., 1] c-momentum.
//   field  (B, 3, F): pic * u + du on the faces (m/s).
//   phi    (B, R, R, R): cell potential (kg/(m s)).
//   entry  8 values per active cell: src, coef, then 1/rho_f of its faces x-, x+, y-, y+, z-, z+.
// No torch headers: nvcc compiles the .cu that includes this without them.
#pragma once

#include <math.h>
#include <stdint.h>

#if defined(__CUDACC__)
#define AMS_GRID_HD __host__ __device__ __forceinline__
#else
#define AMS_GRID_HD inline
#endif

namespace ams_torch {
namespace grid {

constexpr double kActiveFaceDensity = 1e-6; // faces with M <= 1e-6 rho0 h^3 carry no gradient (pressure.py)
constexpr int kEntry = 8;                   // values per active cell

AMS_GRID_HD int64_t num_faces(int64_t r) { return (r + 1) * r * r; }

AMS_GRID_HD float grid_floor(float a) { return floorf(a); }
AMS_GRID_HD double grid_floor(double a) { return floor(a); }

// Head-frame position xl = R^T (x - T) and velocity relative to the rigid motion,
// vl = R^T (v - V - W x (x - T)).
template <class T>
AMS_GRID_HD void to_head(const T* fr, const T* x, const T* v, T* xl, T* vl) {
  const T rel[3] = {x[0] - fr[9], x[1] - fr[10], x[2] - fr[11]};
  const T* w = fr + 15;
  const T cr[3] = {w[1] * rel[2] - w[2] * rel[1], w[2] * rel[0] - w[0] * rel[2], w[0] * rel[1] - w[1] * rel[0]};
  const T vr[3] = {v[0] - fr[12] - cr[0], v[1] - fr[13] - cr[1], v[2] - fr[14] - cr[2]};
  for (int i = 0; i < 3; ++i) {
    xl[i] = fr[i] * rel[0] + fr[3 + i] * rel[1] + fr[6 + i] * rel[2];
    vl[i] = fr[i] * vr[0] + fr[3 + i] * vr[1] + fr[6 + i] * vr[2];
  }
}

// Cell coordinate along axis a of a head-frame point (cell i spans [i, i+1)).
template <class T>
AMS_GRID_HD T cell_coord(const T* xl, const T* origin, T h, int a) {
  return (xl[a] - origin[a]) / h;
}

// Trilinear stencil of head-frame point xl on the c-face grid: returns the flat index of the
// lower corner, fills the 8 weights and index offsets (corner (i, j, k) at 4i + 2j + k).
// Per axis the lower corner is clamped to [0, n-2] and only weights of corners inside are
// kept; far outside (or NaN) every weight is zero.
template <class T>
AMS_GRID_HD int64_t face_stencil(const T* xl, const T* origin, T h, int64_t r, int c, T* w, int64_t* off) {
  const int64_t n[3] = {c == 0 ? r + 1 : r, c == 1 ? r + 1 : r, c == 2 ? r + 1 : r};
  int64_t bc[3];
  T wa[3][2];
  for (int a = 0; a < 3; ++a) {
    T g = cell_coord(xl, origin, h, a);
    if (a != c) g = g - T(0.5);
    const T base = grid_floor(g);
    const T f = g - base;
    T cl = base;
    if (!(cl >= T(-2))) cl = T(-2); // also NaN
    if (cl > T(r + 2)) cl = T(r + 2);
    const int64_t i0 = int64_t(cl);
    const int64_t b = i0 < 0 ? 0 : (i0 > n[a] - 2 ? n[a] - 2 : i0);
    const int64_t d = i0 - b;
    const T one_f = T(1) - f;
    wa[a][0] = d == 0 ? one_f : (d == -1 ? f : T(0));
    wa[a][1] = d == 0 ? f : (d == 1 ? one_f : T(0));
    bc[a] = b;
  }
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) {
        w[4 * i + 2 * j + k] = wa[0][i] * wa[1][j] * wa[2][k];
        off[4 * i + 2 * j + k] = (i * n[1] + j) * n[2] + k;
      }
  return (bc[0] * n[1] + bc[1]) * n[2] + bc[2];
}

// P2G of one particle (head frame) into one scene's faces (3 F 2 values); `add(ptr, value)`
// accumulates (plain += on the CPU, atomicAdd on the GPU).
template <class T, class Add>
AMS_GRID_HD void p2g_scatter(const T* xl, const T* vl, T m, const T* origin, T h, int64_t r, T* faces, Add add) {
  const int64_t nf = num_faces(r);
  for (int c = 0; c < 3; ++c) {
    T w[8];
    int64_t off[8];
    const int64_t base = face_stencil(xl, origin, h, r, c, w, off);
    const T mv = m * vl[c];
    T* fc = faces + 2 * (c * nf + base);
    for (int k = 0; k < 8; ++k) {
      add(fc + 2 * off[k], w[k] * m);
      add(fc + 2 * off[k] + 1, w[k] * mv);
    }
  }
}

// Constants of the pressure solve, in T as the torch code rounds them.
template <class T>
struct PressureConsts {
  T h, h2, h3, eps, rho0, dt, omega, one_minus_omega, stiffness, pic;
};

template <class T>
AMS_GRID_HD PressureConsts<T> pressure_consts(double h, T rho0, T dt, double omega, double stiffness, double pic) {
  PressureConsts<T> k;
  const double h3 = h * h * h;
  k.h = T(h);
  k.h2 = T(h * h);
  k.h3 = T(h3);
  k.eps = rho0 * T(kActiveFaceDensity * h3);
  k.rho0 = rho0;
  k.dt = dt;
  k.omega = T(omega);
  k.one_minus_omega = T(1.0 - omega);
  k.stiffness = T(stiffness);
  k.pic = T(pic);
  return k;
}

// Flat indices of the lower and upper c-face of cell (i, j, k).
AMS_GRID_HD void cell_faces(int64_t r, int64_t i, int64_t j, int64_t k, int c, int64_t* lo, int64_t* hi) {
  if (c == 0) {
    *lo = (i * r + j) * r + k;
    *hi = *lo + r * r;
  } else if (c == 1) {
    *lo = (i * (r + 1) + j) * r + k;
    *hi = *lo + r;
  } else {
    *lo = (i * r + j) * (r + 1) + k;
    *hi = *lo + 1;
  }
}

// Whether cell (i, j, k) of a scene can carry phi: all six faces have mass > eps.
template <class T>
AMS_GRID_HD bool cell_active(const T* faces, int64_t r, int64_t i, int64_t j, int64_t k, T eps) {
  const int64_t nf = num_faces(r);
  for (int c = 0; c < 3; ++c) {
    int64_t lo, hi;
    cell_faces(r, i, j, k, c, &lo, &hi);
    if (!(faces[2 * (c * nf + lo)] > eps) || !(faces[2 * (c * nf + hi)] > eps)) return false;
  }
  return true;
}

// Terms of an active cell: entry = {src, coef, 1/rho_f x6}. Returns src (> 0: the cell pushes).
template <class T>
AMS_GRID_HD T cell_entry(const T* faces, int64_t r, int64_t i, int64_t j, int64_t k, const PressureConsts<T>& q,
                         T* entry) {
  const int64_t nf = num_faces(r);
  T mass[6], vel[6];
  for (int c = 0; c < 3; ++c) {
    int64_t idx[2];
    cell_faces(r, i, j, k, c, &idx[0], &idx[1]);
    for (int s = 0; s < 2; ++s) {
      const T mf = faces[2 * (c * nf + idx[s])];
      const T pf = faces[2 * (c * nf + idx[s]) + 1];
      mass[2 * c + s] = mf;
      vel[2 * c + s] = mf > T(0) ? pf / mf : T(0);
      entry[2 + 2 * c + s] = mf > q.eps ? q.h3 / mf : T(0);
    }
  }
  T total = T(0.5) * (mass[0] + mass[1]);
  total = total + T(0.5) * (mass[2] + mass[3]);
  total = total + T(0.5) * (mass[4] + mass[5]);
  const T rho = total / T(3) / q.h3;
  T div = vel[1] - vel[0];
  div = div + (vel[3] - vel[2]);
  div = div + (vel[5] - vel[4]);
  div = div / q.h;
  T rhs = q.stiffness * (T(1) - q.rho0 / rho) / q.dt;
  if (rho > q.rho0) rhs = rhs > -div ? rhs : -div;
  T diag = entry[2] + entry[3];
  diag = diag + entry[4];
  diag = diag + entry[5];
  diag = diag + entry[6];
  diag = diag + entry[7];
  const T coef = q.omega / diag;
  entry[0] = coef * (q.h2 * rhs);
  entry[1] = coef;
  return entry[0];
}

// Which of the six neighbours of cell (i, j, k) exist: bits x-, x+, y-, y+, z-, z+.
AMS_GRID_HD unsigned neighbour_mask(int64_t r, int64_t i, int64_t j, int64_t k) {
  return unsigned(i > 0) | unsigned(i < r - 1) << 1 | unsigned(j > 0) << 2 | unsigned(j < r - 1) << 3 |
         unsigned(k > 0) << 4 | unsigned(k < r - 1) << 5;
}

// One projected weighted-Jacobi update of an active cell at `phi[cell]` (its neighbours at
// +-R^2, +-R, +-1 where `mask` says they exist): max(0, src + coef * sum_f phi_nb / rho_f +
// (1 - omega) phi), neighbours outside the grid = 0, summed in the order x-, x+, y-, y+, z-, z+.
template <class T>
AMS_GRID_HD T sweep_cell(const T* phi, int64_t r, int64_t cell, unsigned mask, const T* e, T one_minus_omega) {
  T n = T(0);
  if (mask & 1u) n = n + e[2] * phi[cell - r * r];
  if (mask & 2u) n = n + e[3] * phi[cell + r * r];
  if (mask & 4u) n = n + e[4] * phi[cell - r];
  if (mask & 8u) n = n + e[5] * phi[cell + r];
  if (mask & 16u) n = n + e[6] * phi[cell - 1];
  if (mask & 32u) n = n + e[7] * phi[cell + 1];
  T t = e[0] + e[1] * n;
  t = t + one_minus_omega * phi[cell];
  return t < T(0) ? T(0) : t;
}

// The G2P field of the c-face (a0, a1, a2) (flat index `face` in its grid) of one scene:
// pic * u + du with u = mom / M (0 where massless) and du = -((phi_hi - phi_lo) / h) * h^3 / M
// (0 at or below eps); phi_hi is the cell with the face's indices (when inside), phi_lo the
// one below along c, phi = 0 outside the grid.
template <class T>
AMS_GRID_HD T face_field(const T* faces, const T* phi, int64_t r, int c, int64_t a0, int64_t a1, int64_t a2,
                         int64_t face, const PressureConsts<T>& q) {
  const int64_t nf = num_faces(r);
  const T mf = faces[2 * (c * nf + face)];
  if (!(mf > T(0))) return T(0); // u = 0 and du = -(g * 0): exactly 0 for a finite phi
  const T pf = faces[2 * (c * nf + face) + 1];
  const T u = pf / mf;
  const T inv = mf > q.eps ? q.h3 / mf : T(0);
  const int64_t along = c == 0 ? a0 : (c == 1 ? a1 : a2);
  const int64_t stride = c == 0 ? r * r : (c == 1 ? r : 1);
  const int64_t cell = (a0 * r + a1) * r + a2;
  const T phi_hi = along < r ? phi[cell] : T(0);
  const T phi_lo = along > 0 ? phi[cell - stride] : T(0);
  const T g = (phi_hi - phi_lo) / q.h;
  const T du = -(g * inv);
  return q.pic * u + du;
}

// G2P of one particle: FLIP/PIC blend in the head frame, back to the world. x', v' = x + dt R dv,
// v + R dv with dv = I(field) - pic * wsum * vl (0 when pinned).
template <class T>
AMS_GRID_HD void g2p_particle(const T* fr, const T* x, const T* v, const T* field, const T* origin, T h, int64_t r,
                              T pic, bool free, T dt, T* xo, T* vo) {
  T xl[3], vl[3];
  to_head(fr, x, v, xl, vl);
  const int64_t nf = num_faces(r);
  T dv[3];
  for (int c = 0; c < 3; ++c) {
    T w[8];
    int64_t off[8];
    const T* fc = field + c * nf + face_stencil(xl, origin, h, r, c, w, off);
    T s = T(0), ws = T(0);
    for (int k = 0; k < 8; ++k) {
      s = s + fc[off[k]] * w[k];
      ws = ws + w[k];
    }
    dv[c] = free ? s - pic * ws * vl[c] : T(0);
  }
  const T dx[3] = {dt * dv[0], dt * dv[1], dt * dv[2]};
  for (int i = 0; i < 3; ++i) {
    xo[i] = x[i] + (fr[3 * i] * dx[0] + fr[3 * i + 1] * dx[1] + fr[3 * i + 2] * dx[2]);
    vo[i] = v[i] + (fr[3 * i] * dv[0] + fr[3 * i + 1] * dv[1] + fr[3 * i + 2] * dv[2]);
  }
}

} // namespace grid
} // namespace ams_torch
