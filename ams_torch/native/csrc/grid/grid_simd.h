// SIMD lanes for the CPU grid kernels: W particles at once (GCC/Clang vector extensions, 32-byte
// vectors: 8 float or 4 double particles). Every routine here is the lane-by-lane version of a
// per-particle routine of grid.h (to_head, particle_blocks, axis_stencil, corner_faces, G2P's
// sums), with the same floating-point operations in the same order; only the bookkeeping (which
// lanes, table reads, integer offsets) is arranged for vectors. Host only; AMS_GRID_SIMD is 0
// where AVX2 or vector extensions are missing, and grid_cpu.cpp then calls grid.h's routines.
#pragma once

#include "grid/grid.h"

#if (defined(__GNUC__) || defined(__clang__)) && defined(__AVX2__) && !defined(__CUDACC__)
#define AMS_GRID_SIMD 1
#include <immintrin.h>

#include <cstring>

namespace ams_torch {
namespace grid {
namespace simd {

template <class T>
struct Lanes;

template <>
struct Lanes<float> {
  static constexpr int W = 8;
  typedef float V __attribute__((vector_size(32)));
  typedef int32_t E;
  typedef int32_t I __attribute__((vector_size(32))); // lane masks and indices (same lane width)
  static V floor(V a) { return (V)_mm256_floor_ps((__m256)a); }
};

template <>
struct Lanes<double> {
  static constexpr int W = 4;
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t E;
  typedef int64_t I __attribute__((vector_size(32)));
  static V floor(V a) { return (V)_mm256_floor_pd((__m256d)a); }
};

template <class T>
using VecT = typename Lanes<T>::V;

// out[lane] = base[idx[lane]] where mask[lane], else `fallback` (AVX2 gathers for float lanes, a
// loop for double lanes).
inline Lanes<float>::I gather(const int32_t* base, Lanes<float>::I idx, Lanes<float>::I mask, int32_t fallback) {
  return (Lanes<float>::I)_mm256_mask_i32gather_epi32(_mm256_set1_epi32(fallback), base, (__m256i)idx, (__m256i)mask,
                                                       4);
}

inline Lanes<float>::V gather(const float* base, Lanes<float>::I idx, Lanes<float>::I mask) {
  return (Lanes<float>::V)_mm256_mask_i32gather_ps(_mm256_setzero_ps(), base, (__m256i)idx, (__m256)mask, 4);
}

inline Lanes<double>::I gather(const int32_t* base, Lanes<double>::I idx, Lanes<double>::I mask, int32_t fallback) {
  Lanes<double>::I out;
  for (int l = 0; l < 4; ++l) out[l] = mask[l] ? base[idx[l]] : fallback;
  return out;
}

inline Lanes<double>::V gather(const double* base, Lanes<double>::I idx, Lanes<double>::I mask) {
  return (Lanes<double>::V)_mm256_mask_i64gather_pd(_mm256_setzero_pd(), base, (__m256i)idx, (__m256d)mask, 8);
}

inline Lanes<double>::I gather(const int64_t* base, Lanes<double>::I idx) {
  return (Lanes<double>::I)_mm256_i64gather_epi64(reinterpret_cast<const long long*>(base), (__m256i)idx, 8);
}

inline Lanes<float>::I gather(const int32_t* base, Lanes<float>::I idx) {
  return (Lanes<float>::I)_mm256_i32gather_epi32(base, (__m256i)idx, 4);
}
template <class T>
using IntT = typename Lanes<T>::I;

template <class T>
inline VecT<T> splat(T c) {
  return VecT<T>{} + c;
}

template <class T>
inline IntT<T> isplat(int64_t c) {
  return IntT<T>{} + typename Lanes<T>::E(c);
}

// to_head for W particles: fr one scene's frame; x, v (W, 3) lanes in xs, vs (per axis).
template <class T>
inline void to_head(const T* fr, const VecT<T> x[3], const VecT<T> v[3], VecT<T> xl[3], VecT<T> vl[3]) {
  using V = VecT<T>;
  const V rel[3] = {x[0] - fr[9], x[1] - fr[10], x[2] - fr[11]};
  const T* w = fr + 15;
  const V cr[3] = {w[1] * rel[2] - w[2] * rel[1], w[2] * rel[0] - w[0] * rel[2], w[0] * rel[1] - w[1] * rel[0]};
  const V vr[3] = {v[0] - fr[12] - cr[0], v[1] - fr[13] - cr[1], v[2] - fr[14] - cr[2]};
  for (int i = 0; i < 3; ++i) {
    xl[i] = fr[i] * rel[0] + fr[3 + i] * rel[1] + fr[6 + i] * rel[2];
    vl[i] = fr[i] * vr[0] + fr[3 + i] * vr[1] + fr[6 + i] * vr[2];
  }
}

// clamped_floor of grid.h, lane by lane.
template <class T>
inline IntT<T> clamped_floor(VecT<T> g, int64_t r) {
  using V = VecT<T>;
  V f = Lanes<T>::floor(g);
  f = f >= T(-2) ? f : splat<T>(T(-2)); // also NaN
  f = f > T(r + 2) ? splat<T>(T(r + 2)) : f;
  return __builtin_convertvector(f, IntT<T>);
}

// axis_stencil of grid.h, lane by lane: lower corner and the two weights.
template <class T>
inline IntT<T> axis_stencil(VecT<T> g, int64_t n, int64_t r, VecT<T>& w0, VecT<T>& w1) {
  using V = VecT<T>;
  using I = IntT<T>;
  const V f = g - Lanes<T>::floor(g);
  const I i0 = clamped_floor<T>(g, r);
  I b = i0 < 0 ? I{} : i0;
  b = b > isplat<T>(n - 2) ? isplat<T>(n - 2) : b;
  const I d = i0 - b; // 0 inside; -1 / 1 half outside; else fully outside
  const V one_f = T(1) - f;
  w0 = d == 0 ? one_f : (d == -1 ? f : V{});
  w1 = d == 0 ? f : (d == 1 ? one_f : V{});
  return b;
}

// The stencils of a batch of W particles (lanes), as grid.h's particle_stencil, pool_corners and
// corner_faces give them per particle: per component c and corner n = 4i + 2j + k the weight and
// the face offset in the scene's pool (negative: no slot).
template <class T>
struct Batch {
  static constexpr int W = Lanes<T>::W;
  VecT<T> w[3][8];
  IntT<T> face[3][8];
  VecT<T> wv[2][3][2]; // the 1-D weights [variant][axis][corner] (the adjoints read them)
};

// Corners of component C: block[e * W + lane] is the pool offset of cube block e of that lane.
template <int C, class T>
inline void batch_corners(const IntT<T> base[2][3], const VecT<T> wv[2][3][2], const IntT<T> first[3],
                          const typename Lanes<T>::E* block, Batch<T>& bt) {
  using I = IntT<T>;
  constexpr int W = Lanes<T>::W;
  constexpr int v0 = C == 0 ? 0 : 1, v1 = C == 1 ? 0 : 1, v2 = C == 2 ? 0 : 1;
  constexpr int var[3] = {v0, v1, v2};
  I lane_id;
  for (int l = 0; l < W; ++l) lane_id[l] = l;
  I bit[3][2], loc[3][2];
  for (int a = 0; a < 3; ++a)
    for (int d = 0; d < 2; ++d) {
      const I q = base[var[a]][a] + d;
      bit[a][d] = (q >> 2) - first[a];
      loc[a][d] = q & 3;
    }
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j) {
      const VecT<T> w01 = wv[v0][0][i] * wv[v1][1][j];
      for (int k = 0; k < 2; ++k) {
        const int n = 4 * i + 2 * j + k;
        bt.w[C][n] = w01 * wv[v2][2][k];
        const I cube = (bit[0][i] << 2) + (bit[1][j] << 1) + bit[2][k];
        const I local = (loc[0][i] << 4) + (loc[1][j] << 2) + loc[2][k] + C * kBlockCells;
        bt.face[C][n] = gather(block, cube * W + lane_id) + local;
      }
    }
}

// Stencils of the first `lanes` lanes of xl (head frame) into bt; table: one scene's block table.
template <class T>
inline void batch_stencil(const VecT<T> xl[3], const T* origin, T h, int64_t r, int64_t nb, const int32_t* table,
                          int lanes, Batch<T>& bt) {
  using I = IntT<T>;
  constexpr int W = Lanes<T>::W;
  I base[2][3];
  VecT<T> wv[2][3][2];
  I first[3], span[3];
  for (int a = 0; a < 3; ++a) {
    const VecT<T> g = (xl[a] - origin[a]) / h;
    base[0][a] = axis_stencil<T>(g, r + 1, r, wv[0][a][0], wv[0][a][1]);
    base[1][a] = axis_stencil<T>(g - T(0.5), r, r, wv[1][a][0], wv[1][a][1]);
    const I lo = base[0][a] < base[1][a] ? base[0][a] : base[1][a];
    const I hi = base[0][a] < base[1][a] ? base[1][a] : base[0][a];
    first[a] = lo >> 2;
    span[a] = ((hi + 1) >> 2) - first[a];
  }
  I valid;
  for (int l = 0; l < W; ++l) valid[l] = l < lanes ? -1 : 0;
  alignas(32) typename Lanes<T>::E block[8 * W]; // pool offset of cube block e, lane l at e W + l
  const typename Lanes<T>::E n = typename Lanes<T>::E(nb);
  for (int e = 0; e < 8; ++e) {
    const int i = e >> 2, j = (e >> 1) & 1, k = e & 1;
    const I use = valid & (span[0] >= i) & (span[1] >= j) & (span[2] >= k);
    const I id = ((first[0] + i) * n + first[1] + j) * n + first[2] + k;
    const I slot = gather(table, id, use, -1);
    const I off = slot < 0 ? isplat<T>(kNoBlock) : slot * (3 * kBlockCells);
    for (int l = 0; l < W; ++l) block[e * W + l] = off[l];
  }
  batch_corners<0, T>(base, wv, first, block, bt);
  batch_corners<1, T>(base, wv, first, block, bt);
  batch_corners<2, T>(base, wv, first, block, bt);
  for (int v = 0; v < 2; ++v)
    for (int a = 0; a < 3; ++a)
      for (int d = 0; d < 2; ++d) bt.wv[v][a][d] = wv[v][a][d];
}

// grid_adjoint.h's axis_stencil_slope, lane by lane: dw/dg of the two weights.
template <class T>
inline void axis_slope(VecT<T> g, int64_t n, int64_t r, VecT<T>& s0, VecT<T>& s1) {
  using V = VecT<T>;
  using I = IntT<T>;
  const I i0 = clamped_floor<T>(g, r);
  I b = i0 < 0 ? I{} : i0;
  b = b > isplat<T>(n - 2) ? isplat<T>(n - 2) : b;
  const I d = i0 - b;
  const V one = splat<T>(T(1)), minus = splat<T>(T(-1)), zero = V{};
  s0 = d == 0 ? minus : (d == -1 ? one : zero);
  s1 = d == 0 ? one : (d == 1 ? minus : zero);
}

// The slopes of a batch's 1-D weights [variant][axis][corner] (grid_adjoint.h's particle_slopes).
template <class T>
inline void batch_slopes(const VecT<T> xl[3], const T* origin, T h, int64_t r, VecT<T> dw[2][3][2]) {
  for (int a = 0; a < 3; ++a) {
    const VecT<T> g = (xl[a] - origin[a]) / h;
    axis_slope<T>(g, r + 1, r, dw[0][a][0], dw[0][a][1]);
    axis_slope<T>(g - T(0.5), r, r, dw[1][a][0], dw[1][a][1]);
  }
}

// grid_adjoint.h's corner_weights_adjoint for component C, lane by lane.
template <int C, class T>
inline void corner_weights_adjoint(const VecT<T> wv[2][3][2], const VecT<T> gw[8], VecT<T> g1[2][3][2]) {
  constexpr int v0 = C == 0 ? 0 : 1, v1 = C == 1 ? 0 : 1, v2 = C == 2 ? 0 : 1;
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j) {
      const VecT<T> w01 = wv[v0][0][i] * wv[v1][1][j];
      VecT<T> g01 = VecT<T>{};
      for (int k = 0; k < 2; ++k) {
        const VecT<T> gk = gw[4 * i + 2 * j + k];
        g01 = g01 + gk * wv[v2][2][k];
        g1[v2][2][k] = g1[v2][2][k] + gk * w01;
      }
      g1[v0][0][i] = g1[v0][0][i] + g01 * wv[v1][1][j];
      g1[v1][1][j] = g1[v1][1][j] + g01 * wv[v0][0][i];
    }
}

template <class T>
inline void corner_weights_adjoint_rt(int c, const VecT<T> wv[2][3][2], const VecT<T> gw[8], VecT<T> g1[2][3][2]) {
  if (c == 0)
    corner_weights_adjoint<0, T>(wv, gw, g1);
  else if (c == 1)
    corner_weights_adjoint<1, T>(wv, gw, g1);
  else
    corner_weights_adjoint<2, T>(wv, gw, g1);
}

// grid_adjoint.h's stencil_position_adjoint, lane by lane.
template <class T>
inline void position_adjoint(const VecT<T> xl[3], const T* origin, T h, int64_t r, const VecT<T> g1[2][3][2],
                             VecT<T> g_xl[3]) {
  VecT<T> dw[2][3][2];
  batch_slopes<T>(xl, origin, h, r, dw);
  for (int a = 0; a < 3; ++a) {
    const VecT<T> gg = (dw[0][a][0] * g1[0][a][0] + dw[0][a][1] * g1[0][a][1]) +
                       (dw[1][a][0] * g1[1][a][0] + dw[1][a][1] * g1[1][a][1]);
    g_xl[a] = gg / h;
  }
}

// The blocks the particles of a batch touch (grid.h's particle_blocks, lane by lane): per axis the
// first and last block; `inside` false where a particle weighs no face.
template <class T>
inline void batch_blocks(const VecT<T> xl[3], const T* origin, T h, int64_t r, IntT<T> first[3], IntT<T> last[3],
                         IntT<T>& inside) {
  using I = IntT<T>;
  inside = I{} - 1;
  for (int a = 0; a < 3; ++a) {
    const I f = clamped_floor<T>((xl[a] - origin[a]) / h, r);
    const I lo = f - 1 < 0 ? I{} : f - 1;
    const I hi = f + 1 > isplat<T>(r) ? isplat<T>(r) : f + 1;
    inside = inside & (lo <= hi);
    first[a] = lo >> 2;
    last[a] = hi >> 2;
  }
}

// G2P of a batch: the change dv (head frame) of the first `lanes` lanes, grid.h's g2p_particle
// sums lane by lane; field: one scene's pool field.
template <class T>
inline void batch_change(const Batch<T>& bt, const T* field, const VecT<T> vl[3], IntT<T> free, T pic,
                         VecT<T> dv[3]) {
  using V = VecT<T>;
  for (int c = 0; c < 3; ++c) {
    V acc{}, ws{};
    for (int n = 0; n < 8; ++n) {
      const IntT<T> has = bt.face[c][n] >= 0;
      const V val = gather(field, bt.face[c][n], has);
      acc = has ? acc + val * bt.w[c][n] : acc;
      ws = ws + bt.w[c][n];
    }
    dv[c] = free ? acc - pic * ws * vl[c] : V{};
  }
}

// The per-slot passes of the pressure op over one slot's pool faces (slot, c, l, {mass, momentum}),
// 8 float or 4 double cells at a time: the interleaved pairs are split into a mass and a momentum
// vector (in cell order), then the same comparisons and the same one-rounding operations as the
// scalar code, so the results are bit for bit the scalar ones. Only the split and the mask's bits
// are type-specific intrinsics.
inline void split_pairs(const float* f, VecT<float>& mass, VecT<float>& mom) { // cells l .. l + 7 of f = &pair l
  const __m256 a = _mm256_loadu_ps(f), b = _mm256_loadu_ps(f + 8);
  const __m256 m = _mm256_shuffle_ps(a, b, _MM_SHUFFLE(2, 0, 2, 0)); // l, l+1, l+4, l+5 | l+2, l+3, l+6, l+7
  const __m256 p = _mm256_shuffle_ps(a, b, _MM_SHUFFLE(3, 1, 3, 1));
  mass = (VecT<float>)_mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(m), _MM_SHUFFLE(3, 1, 2, 0)));
  mom = (VecT<float>)_mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(p), _MM_SHUFFLE(3, 1, 2, 0)));
}

inline void split_pairs(const double* f, VecT<double>& mass, VecT<double>& mom) { // cells l .. l + 3
  const __m256d a = _mm256_loadu_pd(f), b = _mm256_loadu_pd(f + 4);
  mass = (VecT<double>)_mm256_permute4x64_pd(_mm256_shuffle_pd(a, b, 0x0), _MM_SHUFFLE(3, 1, 2, 0)); // l, l+2, l+1, l+3 → order
  mom = (VecT<double>)_mm256_permute4x64_pd(_mm256_shuffle_pd(a, b, 0xF), _MM_SHUFFLE(3, 1, 2, 0));
}

inline uint32_t mask_bits(IntT<float> m) { return uint32_t(_mm256_movemask_ps((__m256)m)); }
inline uint32_t mask_bits(IntT<double> m) { return uint32_t(_mm256_movemask_pd((__m256d)m)); }

// Bit l: the three lower faces of cell l (slot faces f, 3 × 64 pairs) have mass > eps (false for NaN).
template <class T>
inline uint64_t lower_faces_massive(const T* f, T eps) {
  constexpr int W = Lanes<T>::W;
  uint64_t bits = 0;
  for (int l = 0; l < kBlockCells; l += W) {
    IntT<T> all = IntT<T>{} - 1;
    for (int c = 0; c < 3; ++c) {
      VecT<T> mass, mom;
      split_pairs(f + 2 * (c * kBlockCells + l), mass, mom);
      all = all & (mass > eps);
    }
    bits |= uint64_t(mask_bits(all)) << l;
  }
  return bits;
}

// The field of a slot where phi cannot reach: out[i] = mass > 0 ? pic * (mom / mass) : 0 for the
// 3 × 64 faces of f (grid.h's face_field with du = 0).
template <class T>
inline void quiet_field(const T* f, T pic, T* out) {
  constexpr int W = Lanes<T>::W;
  for (int i = 0; i < 3 * kBlockCells; i += W) {
    VecT<T> mass, mom;
    split_pairs(f + 2 * i, mass, mom);
    const IntT<T> has = mass > T(0);
    const VecT<T> u = mom / (has ? mass : VecT<T>{} + T(1));
    const VecT<T> field = has ? pic * u : VecT<T>{};
    std::memcpy(out + i, &field, sizeof(field));
  }
}

} // namespace simd
} // namespace grid
} // namespace ams_torch
#else
#define AMS_GRID_SIMD 0
#endif
