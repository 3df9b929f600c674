// Banded block Cholesky solve of one strand's implicit system (SPEC §4), written once for
// the host (CPU kernel, banded_cpu.cpp) and the device (CUDA kernel, banded_cuda.cu).
//
// The matrix A is symmetric positive definite, made of 3×3 blocks, with 3 blocks on each side
// of the diagonal. One strand's data is N "rows" of 36 values:
//
//     row i, element 9 k + 3 r + c  =  A[i, i-k](r, c)      k = 0..3, r, c = 0..2
//
// i.e. exactly the contiguous tail (4, 3, 3) of torch's `blocks` tensor (..., N, 4, 3, 3).
// Entries are read as follows, and only these (the autograd rule in ops.py matches it):
//   * k >= 1, i >= k: the whole 3×3 block A[i, i-k]; the upper band is its transpose.
//   * k = 0: the lower triangle (r >= c) of the diagonal block; its strict upper triangle is
//     never read (the block is taken to be symmetric).
//   * k > i: never read.
//
// The factorisation A = L Lᵀ is done in place: after the solve, row i holds L[i, i-k] for
// k >= 1 and, in the diagonal block, the lower triangle of L[i, i] plus the reciprocals of
// its three diagonal entries in the otherwise unused upper slots (0,1), (0,2), (1,2). Each 3×3
// pivot is factored by closed-form Cholesky and applied by forward/backward substitution; no
// 3×3 inverse is ever formed (backward stability on stiff strands, SPEC §4). The right-hand
// side (N rows of 3) is overwritten by the forward sweep (z = L⁻¹ b) and then by the backward
// sweep (x = L⁻ᵀ z).
//
// Layout is abstracted by `Lanes<V, T>`: element e of the strand is `*(V*)(base + e*stride)`.
//   * CUDA: V = T, base = workspace + strand, stride = number of strands, so consecutive
//     threads touch consecutive addresses (strand-interleaved, coalesced).
//   * CPU:  V = a SIMD vector of W values of T, base = per-thread scratch, stride = W, so W
//     strands are solved at once, lane by lane, with the same arithmetic.
// `LaneMath<V>` supplies sqrt and reciprocal for V (scalars here; vectors in banded_simd.h).
// Arithmetic is + - * on V plus LaneMath, so the CPU build runs the GPU's operation sequence.
// A non-positive pivot gives NaN (the simulator's divergence guard reports it).
#pragma once

#include <math.h>
#include <stdint.h>

#if defined(__CUDACC__)
#define AMS_HD __host__ __device__ __forceinline__
#else
#define AMS_HD inline
#endif

// Full unrolling of the fixed-size (3×3, band 3) loops, so that blocks live in registers.
#if defined(__CUDACC__) || defined(__clang__)
#define AMS_UNROLL _Pragma("unroll")
#elif defined(__GNUC__)
#define AMS_UNROLL _Pragma("GCC unroll 16")
#else
#define AMS_UNROLL
#endif

namespace ams_torch {
namespace banded {

constexpr int kBand = 3;                   // blocks on each side of the diagonal
constexpr int kRowElems = (kBand + 1) * 9; // values per matrix row of one strand (36)
constexpr int kRhsElems = 3;               // values per right-hand-side row

template <class V>
struct LaneMath;

template <>
struct LaneMath<float> {
  static AMS_HD float sqrt(float x) { return ::sqrtf(x); }
  static AMS_HD float recip(float x) { return 1.0f / x; }
};

template <>
struct LaneMath<double> {
  static AMS_HD double sqrt(double x) { return ::sqrt(x); }
  static AMS_HD double recip(double x) { return 1.0 / x; }
};

// Strided view of one strand (or of W strands at once, when V is a W-lane vector).
template <class V, class T>
struct Lanes {
  T* base;
  int64_t stride;
  AMS_HD V& operator[](int64_t e) const { return *reinterpret_cast<V*>(base + e * stride); }
};

// Factor row i of the matrix (K = min(i, 3) earlier rows in the band) and do row i of the
// forward sweep L z = b.
template <int K, class V, class T>
AMS_HD void factor_forward_row(const Lanes<V, T>& a, const Lanes<V, T>& b, int64_t i) {
  using M = LaneMath<V>;
  const int64_t ri = i * kRowElems;
  V li[kBand + 1][9]; // li[k] = L[i, i-k] for k = 1..K

  // Off-diagonal blocks, left to right (k = K .. 1): L[i,j] L[j,j]ᵀ = A[i,j] - Σ_m L[i,m] L[j,m]ᵀ
  // over the band columns m < j of both rows.
AMS_UNROLL
  for (int k = K; k >= 1; --k) {
    const int64_t rj = (i - k) * kRowElems;
    V c[9];
AMS_UNROLL
    for (int e = 0; e < 9; ++e) c[e] = a[ri + 9 * k + e];
AMS_UNROLL
    for (int km = K; km > k; --km) { // m = i - km; L[j, m] is block km - k of row j
      const int64_t bj = rj + 9 * (km - k);
      V ljm[9];
AMS_UNROLL
      for (int e = 0; e < 9; ++e) ljm[e] = a[bj + e];
AMS_UNROLL
      for (int r = 0; r < 3; ++r) {
AMS_UNROLL
        for (int q = 0; q < 3; ++q) {
          c[3 * r + q] = c[3 * r + q] - li[km][3 * r + 0] * ljm[3 * q + 0] -
                         li[km][3 * r + 1] * ljm[3 * q + 1] - li[km][3 * r + 2] * ljm[3 * q + 2];
        }
      }
    }
    // Solve X L[j,j]ᵀ = C row by row: L[j,j] xᵣ = cᵣ (forward substitution).
    const V l00 = a[rj + 0], l10 = a[rj + 3], l11 = a[rj + 4];
    const V l20 = a[rj + 6], l21 = a[rj + 7];
    const V d0 = a[rj + 1], d1 = a[rj + 2], d2 = a[rj + 5]; // 1/l00, 1/l11, 1/l22
AMS_UNROLL
    for (int r = 0; r < 3; ++r) {
      const V x0 = c[3 * r + 0] * d0;
      const V x1 = (c[3 * r + 1] - l10 * x0) * d1;
      const V x2 = (c[3 * r + 2] - l20 * x0 - l21 * x1) * d2;
      li[k][3 * r + 0] = x0;
      li[k][3 * r + 1] = x1;
      li[k][3 * r + 2] = x2;
      a[ri + 9 * k + 3 * r + 0] = x0;
      a[ri + 9 * k + 3 * r + 1] = x1;
      a[ri + 9 * k + 3 * r + 2] = x2;
    }
  }

  // Diagonal pivot: D = A[i,i] - Σ_k L[i,i-k] L[i,i-k]ᵀ (lower triangle), then D = L[i,i] L[i,i]ᵀ.
  V s00 = a[ri + 0], s10 = a[ri + 3], s11 = a[ri + 4];
  V s20 = a[ri + 6], s21 = a[ri + 7], s22 = a[ri + 8];
AMS_UNROLL
  for (int k = 1; k <= K; ++k) {
    const V* p = li[k];
    s00 = s00 - p[0] * p[0] - p[1] * p[1] - p[2] * p[2];
    s10 = s10 - p[3] * p[0] - p[4] * p[1] - p[5] * p[2];
    s11 = s11 - p[3] * p[3] - p[4] * p[4] - p[5] * p[5];
    s20 = s20 - p[6] * p[0] - p[7] * p[1] - p[8] * p[2];
    s21 = s21 - p[6] * p[3] - p[7] * p[4] - p[8] * p[5];
    s22 = s22 - p[6] * p[6] - p[7] * p[7] - p[8] * p[8];
  }
  const V l00 = M::sqrt(s00);
  const V d0 = M::recip(l00);
  const V l10 = s10 * d0;
  const V l20 = s20 * d0;
  const V l11 = M::sqrt(s11 - l10 * l10);
  const V d1 = M::recip(l11);
  const V l21 = (s21 - l20 * l10) * d1;
  const V l22 = M::sqrt(s22 - l20 * l20 - l21 * l21);
  const V d2 = M::recip(l22);
  a[ri + 0] = l00;
  a[ri + 1] = d0;
  a[ri + 2] = d1;
  a[ri + 3] = l10;
  a[ri + 4] = l11;
  a[ri + 5] = d2;
  a[ri + 6] = l20;
  a[ri + 7] = l21;
  a[ri + 8] = l22;

  // Forward sweep, row i: L[i,i] z_i = b_i - Σ_k L[i,i-k] z_{i-k}.
  const int64_t bi = i * kRhsElems;
  V r0 = b[bi + 0], r1 = b[bi + 1], r2 = b[bi + 2];
AMS_UNROLL
  for (int k = 1; k <= K; ++k) {
    const int64_t bk = (i - k) * kRhsElems;
    const V z0 = b[bk + 0], z1 = b[bk + 1], z2 = b[bk + 2];
    const V* p = li[k];
    r0 = r0 - p[0] * z0 - p[1] * z1 - p[2] * z2;
    r1 = r1 - p[3] * z0 - p[4] * z1 - p[5] * z2;
    r2 = r2 - p[6] * z0 - p[7] * z1 - p[8] * z2;
  }
  const V y0 = r0 * d0;
  const V y1 = (r1 - l10 * y0) * d1;
  const V y2 = (r2 - l20 * y0 - l21 * y1) * d2;
  b[bi + 0] = y0;
  b[bi + 1] = y1;
  b[bi + 2] = y2;
}

// Row i of the backward sweep Lᵀ x = z, with K = min(N-1-i, 3) later rows in the band:
// L[i,i]ᵀ x_i = z_i - Σ_k L[i+k,i]ᵀ x_{i+k}.
template <int K, class V, class T>
AMS_HD void backward_row(const Lanes<V, T>& a, const Lanes<V, T>& b, int64_t i) {
  const int64_t bi = i * kRhsElems;
  V r0 = b[bi + 0], r1 = b[bi + 1], r2 = b[bi + 2];
AMS_UNROLL
  for (int k = 1; k <= K; ++k) {
    const int64_t lk = (i + k) * kRowElems + 9 * k; // L[i+k, i]
    const int64_t bk = (i + k) * kRhsElems;
    const V x0 = b[bk + 0], x1 = b[bk + 1], x2 = b[bk + 2];
    r0 = r0 - a[lk + 0] * x0 - a[lk + 3] * x1 - a[lk + 6] * x2;
    r1 = r1 - a[lk + 1] * x0 - a[lk + 4] * x1 - a[lk + 7] * x2;
    r2 = r2 - a[lk + 2] * x0 - a[lk + 5] * x1 - a[lk + 8] * x2;
  }
  const int64_t ri = i * kRowElems;
  const V l10 = a[ri + 3], l20 = a[ri + 6], l21 = a[ri + 7];
  const V d0 = a[ri + 1], d1 = a[ri + 2], d2 = a[ri + 5];
  const V x2 = r2 * d2;
  const V x1 = (r1 - l21 * x2) * d1;
  const V x0 = (r0 - l10 * x1 - l20 * x2) * d0;
  b[bi + 0] = x0;
  b[bi + 1] = x1;
  b[bi + 2] = x2;
}

// Solve A x = b for one strand (or W strands in lock-step). `a`: n rows of 36 values, factored
// in place; `b`: n rows of 3 values, overwritten by x.
template <class V, class T>
AMS_HD void solve_strand(const Lanes<V, T>& a, const Lanes<V, T>& b, int64_t n) {
  if (n <= 0) return;
  factor_forward_row<0>(a, b, 0);
  if (n > 1) factor_forward_row<1>(a, b, 1);
  if (n > 2) factor_forward_row<2>(a, b, 2);
  for (int64_t i = 3; i < n; ++i) factor_forward_row<3>(a, b, i);

  backward_row<0>(a, b, n - 1);
  if (n > 1) backward_row<1>(a, b, n - 2);
  if (n > 2) backward_row<2>(a, b, n - 3);
  for (int64_t i = n - 4; i >= 0; --i) backward_row<3>(a, b, i);
}

} // namespace banded
} // namespace ams_torch
