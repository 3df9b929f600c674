// Copies between W strands' arrays and the strand-interleaved layout of the CPU kernels (value e
// of lane l at e·W + l), shared by the banded solver, the fused frame and the collision stage.
// Host only.
//
//   interleave<T, W>(dst, src, count):            dst[e W + l] = src[l][e],  l < W, e < count
//   deinterleave<T, W>(dst, src, count, lanes):   dst[l][e] = src[e W + l],  l < lanes
//
// With AVX and 32-byte lanes (8 float / 4 double strands), blocks of W values of every strand
// are loaded as W vectors, transposed in registers (unpack / shuffle / 128-bit permute) and
// stored as W vectors: 2 W memory operations per W² values instead of 2 W², which made these
// copies the largest single cost of the fused frame (a third of it at 10k × 32). The remainder
// (count mod W) and other widths are copied one value at a time. A pure copy: bit-exact either
// way.
#pragma once

#include <stdint.h>

#if defined(__AVX__)
#include <immintrin.h>
#endif

namespace ams_torch {
namespace banded {

namespace detail {

template <class T, int64_t W>
inline void interleave_scalar(T* dst, const T* const* src, int64_t begin, int64_t count) {
  for (int64_t e = begin; e < count; ++e)
    for (int64_t l = 0; l < W; ++l) dst[e * W + l] = src[l][e];
}

template <class T, int64_t W>
inline void deinterleave_scalar(T* const* dst, const T* src, int64_t begin, int64_t count, int64_t lanes) {
  for (int64_t l = 0; l < lanes; ++l)
    for (int64_t e = begin; e < count; ++e) dst[l][e] = src[e * W + l];
}

#if defined(__AVX__)
// r[i] = row i of an 8 × 8 float matrix -> r[j] = column j.
inline void transpose8(__m256* r) {
  const __m256 t0 = _mm256_unpacklo_ps(r[0], r[1]), t1 = _mm256_unpackhi_ps(r[0], r[1]);
  const __m256 t2 = _mm256_unpacklo_ps(r[2], r[3]), t3 = _mm256_unpackhi_ps(r[2], r[3]);
  const __m256 t4 = _mm256_unpacklo_ps(r[4], r[5]), t5 = _mm256_unpackhi_ps(r[4], r[5]);
  const __m256 t6 = _mm256_unpacklo_ps(r[6], r[7]), t7 = _mm256_unpackhi_ps(r[6], r[7]);
  const __m256 s0 = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(1, 0, 1, 0));
  const __m256 s1 = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(3, 2, 3, 2));
  const __m256 s2 = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(1, 0, 1, 0));
  const __m256 s3 = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(3, 2, 3, 2));
  const __m256 s4 = _mm256_shuffle_ps(t4, t6, _MM_SHUFFLE(1, 0, 1, 0));
  const __m256 s5 = _mm256_shuffle_ps(t4, t6, _MM_SHUFFLE(3, 2, 3, 2));
  const __m256 s6 = _mm256_shuffle_ps(t5, t7, _MM_SHUFFLE(1, 0, 1, 0));
  const __m256 s7 = _mm256_shuffle_ps(t5, t7, _MM_SHUFFLE(3, 2, 3, 2));
  r[0] = _mm256_permute2f128_ps(s0, s4, 0x20);
  r[1] = _mm256_permute2f128_ps(s1, s5, 0x20);
  r[2] = _mm256_permute2f128_ps(s2, s6, 0x20);
  r[3] = _mm256_permute2f128_ps(s3, s7, 0x20);
  r[4] = _mm256_permute2f128_ps(s0, s4, 0x31);
  r[5] = _mm256_permute2f128_ps(s1, s5, 0x31);
  r[6] = _mm256_permute2f128_ps(s2, s6, 0x31);
  r[7] = _mm256_permute2f128_ps(s3, s7, 0x31);
}

// r[i] = row i of a 4 × 4 double matrix -> r[j] = column j.
inline void transpose4(__m256d* r) {
  const __m256d t0 = _mm256_unpacklo_pd(r[0], r[1]), t1 = _mm256_unpackhi_pd(r[0], r[1]);
  const __m256d t2 = _mm256_unpacklo_pd(r[2], r[3]), t3 = _mm256_unpackhi_pd(r[2], r[3]);
  r[0] = _mm256_permute2f128_pd(t0, t2, 0x20);
  r[1] = _mm256_permute2f128_pd(t1, t3, 0x20);
  r[2] = _mm256_permute2f128_pd(t0, t2, 0x31);
  r[3] = _mm256_permute2f128_pd(t1, t3, 0x31);
}
#endif

} // namespace detail

template <class T, int64_t W>
inline void interleave(T* dst, const T* const* src, int64_t count) {
  detail::interleave_scalar<T, W>(dst, src, 0, count);
}

template <class T, int64_t W>
inline void deinterleave(T* const* dst, const T* src, int64_t count, int64_t lanes) {
  detail::deinterleave_scalar<T, W>(dst, src, 0, count, lanes);
}

#if defined(__AVX__)
template <>
inline void interleave<float, 8>(float* dst, const float* const* src, int64_t count) {
  int64_t e = 0;
  for (; e + 8 <= count; e += 8) {
    __m256 r[8];
    for (int l = 0; l < 8; ++l) r[l] = _mm256_loadu_ps(src[l] + e);
    detail::transpose8(r);
    for (int k = 0; k < 8; ++k) _mm256_storeu_ps(dst + (e + k) * 8, r[k]);
  }
  detail::interleave_scalar<float, 8>(dst, src, e, count);
}

template <>
inline void deinterleave<float, 8>(float* const* dst, const float* src, int64_t count, int64_t lanes) {
  int64_t e = 0;
  for (; e + 8 <= count; e += 8) {
    __m256 r[8];
    for (int k = 0; k < 8; ++k) r[k] = _mm256_loadu_ps(src + (e + k) * 8);
    detail::transpose8(r);
    for (int64_t l = 0; l < lanes; ++l) _mm256_storeu_ps(dst[l] + e, r[l]);
  }
  detail::deinterleave_scalar<float, 8>(dst, src, e, count, lanes);
}

template <>
inline void interleave<double, 4>(double* dst, const double* const* src, int64_t count) {
  int64_t e = 0;
  for (; e + 4 <= count; e += 4) {
    __m256d r[4];
    for (int l = 0; l < 4; ++l) r[l] = _mm256_loadu_pd(src[l] + e);
    detail::transpose4(r);
    for (int k = 0; k < 4; ++k) _mm256_storeu_pd(dst + (e + k) * 4, r[k]);
  }
  detail::interleave_scalar<double, 4>(dst, src, e, count);
}

template <>
inline void deinterleave<double, 4>(double* const* dst, const double* src, int64_t count, int64_t lanes) {
  int64_t e = 0;
  for (; e + 4 <= count; e += 4) {
    __m256d r[4];
    for (int k = 0; k < 4; ++k) r[k] = _mm256_loadu_pd(src + (e + k) * 4);
    detail::transpose4(r);
    for (int64_t l = 0; l < lanes; ++l) _mm256_storeu_pd(dst[l] + e, r[l]);
  }
  detail::deinterleave_scalar<double, 4>(dst, src, e, count, lanes);
}
#endif

} // namespace banded
} // namespace ams_torch
