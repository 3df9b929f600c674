// The per-particle, per-cell and per-face arithmetic of the block-sparse hair–hair grid (SPEC §6),
// written once for the host (grid_cpu.cpp) and the device (grid_cuda.cu). The definition is the
// torch code of ams_torch/stages/hair_hair/sparse.py (itself the dense grid of transfer.py and
// pressure.py on the blocks the hair occupies); every function below does the same operations
// in the same order (up to the compiler's fused multiply-adds).
//
// Layouts (all contiguous, one scene's block after another; K slots per scene, nb = R/4 + 1
// blocks per axis, a block = 4^3 cells, local index (4a + b) 4 + e):
//   frame  (B, 6, 3): rows 0-2 the rotation R (world <- head), 3 the translation T (m), 4 the
//          linear velocity V (m/s), 5 the angular velocity W (rad/s, world frame).
//   table  (B, nb^3) int32: slot of each block, -1 where none.
//   blocks (B, K) int32: block id (I nb + J) nb + K of each slot, -1 for unused slots.
//   count  (B,) int32: blocks the hair occupies (count > K: overflow; slots >= min(count, K)
//          are unused and their contents unspecified).
//   faces  (B, K, 3, 64, 2): per slot and component c the block's c-faces, [.., 0] mass (kg),
//          [.., 1] c-momentum.
//   field  (B, K, 3, 64): pic * u + du on the faces (m/s).
//   phi    (B, K, 64): cell potential (kg/(m s)).
//   entry  8 values per active cell: src, coef, then 1/rho_f of its faces x-, x+, y-, y+, z-, z+.
// Slots below are indices within one scene's pool; pointers passed in point at that scene.
// No torch headers: nvcc compiles the .cu that includes this without them.
#pragma once

#include <math.h>
#include <stdint.h>

#if defined(__CUDACC__)
#define AMS_GRID_HD __host__ __device__ __forceinline__
#else
#define AMS_GRID_HD inline
#endif

// Host builds with AVX2 compute a component's eight corner offsets in one register (integer
// arithmetic: the same values as the portable code, which CUDA and other hosts use).
#if defined(__AVX2__) && !defined(__CUDACC__)
#include <immintrin.h>
#define AMS_GRID_AVX2 1
#endif

namespace ams_torch {
namespace grid {

constexpr double kActiveFaceDensity = 1e-6; // faces with M <= 1e-6 rho0 h^3 carry no gradient (pressure.py)
constexpr int kEntry = 8;                   // values per cell entry
constexpr int kBlock = 4;                   // cells per block and axis (sparse.BLOCK)
constexpr int kBlockCells = kBlock * kBlock * kBlock;

AMS_GRID_HD int64_t blocks_per_axis(int64_t r) { return r / kBlock + 1; }

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

// floor(g) clamped to [-2, r + 2] (NaN: -2), as an integer.
template <class T>
AMS_GRID_HD int64_t clamped_floor(T g, int64_t r) {
  T f = grid_floor(g);
  if (!(f >= T(-2))) f = T(-2); // also NaN
  if (f > T(r + 2)) f = T(r + 2);
  return int64_t(f);
}

// The blocks a particle's stencils touch (sparse.block_layout): per axis the first and last
// block of the face indices [f - 1, f + 1] within [0, R]. False when the particle weighs no face.
template <class T>
AMS_GRID_HD bool particle_blocks(const T* xl, const T* origin, T h, int64_t r, int64_t* first, int64_t* last) {
  for (int a = 0; a < 3; ++a) {
    const int64_t f = clamped_floor(cell_coord(xl, origin, h, a), r);
    const int64_t lo = f - 1 < 0 ? 0 : f - 1;
    const int64_t hi = f + 1 > r ? r : f + 1;
    if (lo > hi) return false;
    first[a] = lo / kBlock;
    last[a] = hi / kBlock;
  }
  return true;
}

// Lower corner (clamped to [0, n-2]) and the two weights of a 1-D linear stencil at coordinate
// g on n samples; only weights of samples that exist are kept (transfer.face_corners).
template <class T>
AMS_GRID_HD int64_t axis_stencil(T g, int64_t n, int64_t r, T* w) {
  const T f = g - grid_floor(g);
  const int64_t i0 = clamped_floor(g, r);
  const int64_t b = i0 < 0 ? 0 : (i0 > n - 2 ? n - 2 : i0);
  const int64_t d = i0 - b; // 0 inside; -1 / 1 half outside; else fully outside
  const T one_f = T(1) - f;
  w[0] = d == 0 ? one_f : (d == -1 ? f : T(0));
  w[1] = d == 0 ? f : (d == 1 ? one_f : T(0));
  return b;
}

// A particle's 1-D stencils per axis: variant 0 for the component along that axis (R + 1
// samples at g), variant 1 for the two others (R samples at g - 1/2).
template <class T>
struct ParticleStencil {
  int64_t base[2][3];
  T w[2][3][2];
};

template <class T>
AMS_GRID_HD void particle_stencil(const T* xl, const T* origin, T h, int64_t r, ParticleStencil<T>& s) {
  for (int a = 0; a < 3; ++a) {
    const T g = cell_coord(xl, origin, h, a);
    s.base[0][a] = axis_stencil(g, r + 1, r, s.w[0][a]);
    s.base[1][a] = axis_stencil(g - T(0.5), r, r, s.w[1][a]);
  }
}

// Where a particle's stencils land in the pool. The corners of both variants span at most 3
// indices per axis (lo .. lo + 2, lo the lowest corner), so at most 2 blocks per axis: a "cube" of
// up to 2x2x2 blocks starting at the block of lo. block[4i + 2j + k] is the offset (slot 3 64) of
// cube block (i, j, k) in a scene's pool, or kNoBlock (so that any corner offset added to it stays
// negative) where it has no slot: at most 8 table reads per particle, shared by the components.
// Per variant, axis and corner d, `cube` is the corner's cube index term (4, 2, 1 per axis times
// its block offset) and `local` its local index term (16, 4, 1 per axis times its index in the
// block).
constexpr int32_t kNoBlock = -(int32_t(1) << 30);

struct PoolCorners {
  int32_t block[8];
  uint32_t first[3];
  int32_t cube[2][3][2];
  int32_t local[2][3][2];
};

template <class T>
AMS_GRID_HD void pool_corners(const ParticleStencil<T>& s, int64_t nb, const int32_t* table, PoolCorners& pc) {
  uint32_t span[3];
  for (int a = 0; a < 3; ++a) {
    const uint32_t b0 = uint32_t(s.base[0][a]), b1 = uint32_t(s.base[1][a]); // corner indices are >= 0
    pc.first[a] = (b0 < b1 ? b0 : b1) / kBlock;
    span[a] = ((b0 < b1 ? b1 : b0) + 1) / kBlock - pc.first[a]; // 0 or 1
#if !defined(AMS_GRID_AVX2)
    const uint32_t bases[2] = {b0, b1};
    for (int v = 0; v < 2; ++v)
      for (int d = 0; d < 2; ++d) {
        const uint32_t q = bases[v] + uint32_t(d);
        pc.cube[v][a][d] = int32_t((q / kBlock - pc.first[a]) << (2 - a));
        pc.local[v][a][d] = int32_t((q % kBlock) << (4 - 2 * a));
      }
#endif
  }
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) {
        int32_t slot = -1;
        if (uint32_t(i) <= span[0] && uint32_t(j) <= span[1] && uint32_t(k) <= span[2])
          slot = table[((pc.first[0] + i) * nb + pc.first[1] + j) * nb + pc.first[2] + k];
        pc.block[4 * i + 2 * j + k] = slot < 0 ? kNoBlock : slot * 3 * kBlockCells;
      }
}

// The component-C trilinear stencil in the pool: weights w[4i + 2j + k] of corner (i, j, k) and
// the corner's face offset (slot 3 + C) 64 + local in a scene's pool, negative where its block has
// no slot (sparse.pool_stencil). C is a template argument so that the variant of every axis is a
// constant and the eight corners unroll into register arithmetic.
template <int C, class T>
AMS_GRID_HD void corner_faces(const ParticleStencil<T>& s, const PoolCorners& pc, int32_t* face, T* w) {
  constexpr int v0 = C == 0 ? 0 : 1, v1 = C == 1 ? 0 : 1, v2 = C == 2 ? 0 : 1;
  const T w2[2] = {s.w[v2][2][0], s.w[v2][2][1]};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j) {
      const T w01 = s.w[v0][0][i] * s.w[v1][1][j];
      for (int k = 0; k < 2; ++k) w[4 * i + 2 * j + k] = w01 * w2[k];
    }
#if defined(AMS_GRID_AVX2)
  // corner n = 4i + 2j + k: index base + (i, j, k) per axis, block offset and local index
  const __m256i bit0 = _mm256_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1), bit1 = _mm256_setr_epi32(0, 0, 1, 1, 0, 0, 1, 1),
                bit2 = _mm256_setr_epi32(0, 1, 0, 1, 0, 1, 0, 1), three = _mm256_set1_epi32(3);
  const __m256i q0 = _mm256_add_epi32(_mm256_set1_epi32(int32_t(s.base[v0][0])), bit0);
  const __m256i q1 = _mm256_add_epi32(_mm256_set1_epi32(int32_t(s.base[v1][1])), bit1);
  const __m256i q2 = _mm256_add_epi32(_mm256_set1_epi32(int32_t(s.base[v2][2])), bit2);
  const __m256i b0 = _mm256_sub_epi32(_mm256_srli_epi32(q0, 2), _mm256_set1_epi32(int32_t(pc.first[0])));
  const __m256i b1 = _mm256_sub_epi32(_mm256_srli_epi32(q1, 2), _mm256_set1_epi32(int32_t(pc.first[1])));
  const __m256i b2 = _mm256_sub_epi32(_mm256_srli_epi32(q2, 2), _mm256_set1_epi32(int32_t(pc.first[2])));
  const __m256i cube = _mm256_add_epi32(_mm256_add_epi32(_mm256_slli_epi32(b0, 2), _mm256_slli_epi32(b1, 1)), b2);
  const __m256i l0 = _mm256_slli_epi32(_mm256_and_si256(q0, three), 4);
  const __m256i l1 = _mm256_slli_epi32(_mm256_and_si256(q1, three), 2);
  const __m256i local = _mm256_add_epi32(_mm256_add_epi32(l0, l1),
                                         _mm256_add_epi32(_mm256_and_si256(q2, three), _mm256_set1_epi32(C * kBlockCells)));
  const __m256i blocks = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(pc.block));
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(face),
                      _mm256_add_epi32(_mm256_permutevar8x32_epi32(blocks, cube), local));
#else
  const int32_t c2[2] = {pc.cube[v2][2][0], pc.cube[v2][2][1]};
  const int32_t l2[2] = {pc.local[v2][2][0] + C * kBlockCells, pc.local[v2][2][1] + C * kBlockCells};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j) {
      const int32_t c01 = pc.cube[v0][0][i] + pc.cube[v1][1][j];
      const int32_t l01 = pc.local[v0][0][i] + pc.local[v1][1][j];
      for (int k = 0; k < 2; ++k) face[4 * i + 2 * j + k] = pc.block[c01 + c2[k]] + l01 + l2[k];
    }
#endif
}

// The three components' stencils: calls f(c, face, w) for c = 0, 1, 2.
template <class T, class F>
AMS_GRID_HD void for_each_component(const ParticleStencil<T>& s, const PoolCorners& pc, F f) {
  T w[8];
  int32_t face[8];
  corner_faces<0>(s, pc, face, w);
  f(0, face, w);
  corner_faces<1>(s, pc, face, w);
  f(1, face, w);
  corner_faces<2>(s, pc, face, w);
  f(2, face, w);
}

// P2G of one particle (head frame) into one scene's pool faces; `add(ptr, value)` accumulates
// (plain += on the CPU, atomicAdd on the GPU). Corners without a slot (overflow) are dropped.
template <class T, class Add>
AMS_GRID_HD void p2g_particle(const T* xl, const T* vl, T m, const T* origin, T h, int64_t r, int64_t nb,
                              const int32_t* table, T* faces, Add add) {
  ParticleStencil<T> s;
  particle_stencil(xl, origin, h, r, s);
  PoolCorners pc;
  pool_corners(s, nb, table, pc);
  for_each_component(s, pc, [&](int c, const int32_t* face, const T* w) {
    const T mv = m * vl[c];
    for (int k = 0; k < 8; ++k) {
      if (face[k] < 0) continue;
      add(faces + 2 * face[k], w[k] * m);
      add(faces + 2 * face[k] + 1, w[k] * mv);
    }
  });
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

// The slots of the six blocks next to `block` (x-, x+, y-, y+, z-, z+), -1 where none.
AMS_GRID_HD void slot_neighbours(int64_t block, int64_t nb, const int32_t* table, int32_t* nbr) {
  const int64_t c[3] = {block / (nb * nb), (block / nb) % nb, block % nb};
  for (int d = 0; d < 6; ++d) {
    int64_t n[3] = {c[0], c[1], c[2]};
    n[d >> 1] += (d & 1) ? 1 : -1;
    const bool in = n[d >> 1] >= 0 && n[d >> 1] < nb;
    nbr[d] = in ? table[(n[0] * nb + n[1]) * nb + n[2]] : -1;
  }
}

// The cell next to local cell l of `slot` in direction d (x-, x+, y-, y+, z-, z+): its local
// index, and in *out its slot (`slot`, or the neighbouring block's from nbr; -1 where none).
AMS_GRID_HD int neighbour_cell(int l, int d, int64_t slot, const int32_t* nbr, int64_t* out) {
  const int axis = d >> 1;
  const int stride = axis == 0 ? kBlock * kBlock : (axis == 1 ? kBlock : 1);
  const int coord = (l / stride) % kBlock;
  if (d & 1) {
    if (coord < kBlock - 1) {
      *out = slot;
      return l + stride;
    }
    *out = nbr[d];
    return l - (kBlock - 1) * stride;
  }
  if (coord > 0) {
    *out = slot;
    return l - stride;
  }
  *out = nbr[d];
  return l + (kBlock - 1) * stride;
}

// Mass and momentum of pool face (slot, c, l) of a scene (0 where the slot is -1: no block).
template <class T>
AMS_GRID_HD void face_values(const T* faces, int64_t slot, int c, int l, T* mass, T* momentum) {
  if (slot < 0) {
    *mass = T(0);
    *momentum = T(0);
    return;
  }
  const int64_t f = (slot * 3 + c) * kBlockCells + l;
  *mass = faces[2 * f];
  *momentum = faces[2 * f + 1];
}

// Terms of pool cell (slot, l): entry = {src, coef, 1/rho_f x6}. Returns whether the cell is
// active (all six faces above eps); `entry` is written only then. The lower c-face is the cell's
// own, the upper one the next cell's along c (sparse.pressure_sparse); the lower faces, in the
// cell's own block, are checked first.
template <class T>
AMS_GRID_HD bool cell_entry(const T* faces, int64_t slot, int l, const int32_t* nbr, const PressureConsts<T>& q,
                            T* entry) {
  T mass[6], mom[6];
  for (int c = 0; c < 3; ++c) {
    face_values(faces, slot, c, l, &mass[2 * c], &mom[2 * c]);
    if (!(mass[2 * c] > q.eps)) return false;
  }
  for (int c = 0; c < 3; ++c) {
    int64_t up_slot;
    const int up = neighbour_cell(l, 2 * c + 1, slot, nbr, &up_slot);
    face_values(faces, up_slot, c, up, &mass[2 * c + 1], &mom[2 * c + 1]);
    if (!(mass[2 * c + 1] > q.eps)) return false;
  }
  T vel[6];
  for (int f = 0; f < 6; ++f) {
    vel[f] = mass[f] > T(0) ? mom[f] / mass[f] : T(0);
    entry[2 + f] = q.h3 / mass[f];
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
  return true;
}

// One projected weighted-Jacobi update of pool cell (slot, l) of a scene's phi (K 64 values):
// max(0, src + coef * sum_f phi_nb / rho_f + (1 - omega) phi), neighbours without a slot = 0,
// summed in the order x-, x+, y-, y+, z-, z+. With a zero entry (a cell that is not active) it
// gives 0.
template <class T>
AMS_GRID_HD T sweep_cell(const T* phi, int64_t slot, int l, const int32_t* nbr, const T* e, T one_minus_omega) {
  T n = T(0);
  for (int d = 0; d < 6; ++d) {
    int64_t s;
    const int nl = neighbour_cell(l, d, slot, nbr, &s);
    const T p = s < 0 ? T(0) : phi[s * kBlockCells + nl];
    n = d == 0 ? e[2] * p : n + e[2 + d] * p;
  }
  T t = e[0] + e[1] * n;
  t = t + one_minus_omega * phi[slot * kBlockCells + l];
  return t < T(0) ? T(0) : t;
}

// The G2P field of pool face (slot, c, l) of one scene: pic * u + du with u = mom / M (0 where
// massless) and du = -((phi_hi - phi_lo) / h) * h^3 / M (0 at or below eps); phi_hi is the cell
// with the face's indices, phi_lo the one below along c (0 where it has no slot).
template <class T>
AMS_GRID_HD T face_field(const T* faces, const T* phi, int64_t slot, int c, int l, const int32_t* nbr,
                         const PressureConsts<T>& q) {
  T mf, pf;
  face_values(faces, slot, c, l, &mf, &pf);
  if (!(mf > T(0))) return T(0); // u = 0 and du = -(g * 0): exactly 0 for a finite phi
  const T u = pf / mf;
  const T inv = mf > q.eps ? q.h3 / mf : T(0);
  int64_t lo_slot;
  const int lo = neighbour_cell(l, 2 * c, slot, nbr, &lo_slot);
  const T phi_hi = phi[slot * kBlockCells + l];
  const T phi_lo = lo_slot < 0 ? T(0) : phi[lo_slot * kBlockCells + lo];
  const T g = (phi_hi - phi_lo) / q.h;
  const T du = -(g * inv);
  return q.pic * u + du;
}

// G2P of one particle: FLIP/PIC blend in the head frame, back to the world. x', v' = x + dt R dv,
// v + R dv with dv = I(field) - pic * wsum * vl (0 when pinned); field of one scene's pool.
template <class T>
AMS_GRID_HD void g2p_particle(const T* fr, const T* x, const T* v, const T* field, const int32_t* table, int64_t nb,
                              const T* origin, T h, int64_t r, T pic, bool free, T dt, T* xo, T* vo) {
  T xl[3], vl[3];
  to_head(fr, x, v, xl, vl);
  ParticleStencil<T> st;
  particle_stencil(xl, origin, h, r, st);
  PoolCorners pc;
  pool_corners(st, nb, table, pc);
  T dv[3];
  for_each_component(st, pc, [&](int c, const int32_t* face, const T* w) {
    T acc = T(0), ws = T(0);
    for (int k = 0; k < 8; ++k) {
      if (face[k] >= 0) acc = acc + field[face[k]] * w[k];
      ws = ws + w[k];
    }
    dv[c] = free ? acc - pic * ws * vl[c] : T(0);
  });
  const T dx[3] = {dt * dv[0], dt * dv[1], dt * dv[2]};
  for (int i = 0; i < 3; ++i) {
    xo[i] = x[i] + (fr[3 * i] * dx[0] + fr[3 * i + 1] * dx[1] + fr[3 * i + 2] * dx[2]);
    vo[i] = v[i] + (fr[3 * i] * dv[0] + fr[3 * i + 1] * dv[1] + fr[3 * i + 2] * dv[2]);
  }
}

} // namespace grid
} // namespace ams_torch
