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

#if defined(__AVX__)
namespace detail {
// One AVX register of T and its W×W transpose: 8 floats, or 4 doubles.
inline __m256 load(const float* p) { return _mm256_loadu_ps(p); }
inline __m256d load(const double* p) { return _mm256_loadu_pd(p); }
inline void store(float* p, __m256 v) { _mm256_storeu_ps(p, v); }
inline void store(double* p, __m256d v) { _mm256_storeu_pd(p, v); }
inline void transpose(__m256* r) { transpose8(r); }
inline void transpose(__m256d* r) { transpose4(r); }

// Whether (T, W) is one full AVX register: the widths the register transposes handle.
template <class T, int64_t W>
constexpr bool kRegisterWidth = W * int64_t(sizeof(T)) == 32 && (sizeof(T) == 4 || sizeof(T) == 8);
} // namespace detail
#endif

template <class T, int64_t W>
inline void interleave(T* dst, const T* const* src, int64_t count) {
  int64_t e = 0;
#if defined(__AVX__)
  if constexpr (detail::kRegisterWidth<T, W>) {
    for (; e + W <= count; e += W) {
      decltype(detail::load(dst)) r[W];
      for (int64_t l = 0; l < W; ++l) r[l] = detail::load(src[l] + e);
      detail::transpose(r);
      for (int64_t k = 0; k < W; ++k) detail::store(dst + (e + k) * W, r[k]);
    }
  }
#endif
  detail::interleave_scalar<T, W>(dst, src, e, count);
}

template <class T, int64_t W>
inline void deinterleave(T* const* dst, const T* src, int64_t count, int64_t lanes) {
  int64_t e = 0;
#if defined(__AVX__)
  if constexpr (detail::kRegisterWidth<T, W>) {
    for (; e + W <= count; e += W) {
      decltype(detail::load(src)) r[W];
      for (int64_t k = 0; k < W; ++k) r[k] = detail::load(src + (e + k) * W);
      detail::transpose(r);
      for (int64_t l = 0; l < lanes; ++l) detail::store(dst[l] + e, r[l]);
    }
  }
#endif
  detail::deinterleave_scalar<T, W>(dst, src, e, count, lanes);
}

} // namespace banded
} // namespace ams_torch
