// Lane-wise arithmetic for the per-strand routines of frame.h and ftl.h, written once for the
// host and the device.
//
// A "lane vector" V is either the scalar T itself (CUDA: one thread per strand) or a GCC/Clang
// vector of W values of T (CPU: W strands in lock-step, banded_simd.h). Everything here is
// built from + - * / and comparisons on V, plus LaneMath<V>::sqrt (banded_cholesky.h), so the
// CPU build runs the GPU's operation sequence. Comparisons give a mask (bool for scalars, an
// integer vector for vectors); `select(mask, a, b)` is torch.where.
#pragma once

#include <math.h>
#include <stdint.h>

#include "banded/banded_cholesky.h"

namespace ams_torch {
namespace frame {

using banded::LaneMath;
using banded::Lanes;

// torch.where(m, a, b), lane by lane (both operands are evaluated, as in torch).
template <class M, class V>
AMS_HD V select(const M& m, const V& a, const V& b) {
  return m ? a : b;
}

// A lane vector with every lane equal to c.
template <class V, class T>
AMS_HD V splat(T c) {
  V r{};
  return r + c;
}

template <class V>
AMS_HD V lane_abs(const V& a) {
  return select(a < 0, -a, a);
}

// min / max as torch.minimum / clamp use them on finite values (NaN handling may differ).
template <class V>
AMS_HD V lane_min(const V& a, const V& b) {
  return select(b < a, b, a);
}

template <class V>
AMS_HD V lane_max(const V& a, const V& b) {
  return select(b > a, b, a);
}

// Coefficients of atan on [-tan(π/8), tan(π/8)] (float) or [-0.66, 0.66] (double), from Cephes
// (atanf.c, atan.c): relative error about 1e-7 and 2e-16 respectively.
template <class T>
struct AtanPoly;

template <>
struct AtanPoly<float> {
  static constexpr float kReduce = 0.4142135623730950f; // tan(π/8): above it, atan(z) = π/4 + atan((z-1)/(z+1))
  template <class V>
  static AMS_HD V atan(const V& x) {
    const V z = x * x;
    return (((8.05374449538e-2f * z - 1.38776856032e-1f) * z + 1.99777106478e-1f) * z - 3.33329491539e-1f) * z * x + x;
  }
  static constexpr float kMoreBits = 0.0f;
};

template <>
struct AtanPoly<double> {
  static constexpr double kReduce = 0.66;
  template <class V>
  static AMS_HD V atan(const V& x) {
    const V z = x * x;
    const V p = (((-8.750608600031904122785e-1 * z - 1.615753718733365076637e1) * z - 7.500855792314704667340e1) * z -
                 1.228866684490136173410e2) * z - 6.485021904942025371773e1;
    const V q = ((((z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2) * z + 4.328810604912902668951e2) * z +
                 4.853903996359136964868e2) * z + 1.945506571482613964425e2;
    return x + x * (z * p / q);
  }
  static constexpr double kMoreBits = 6.123233995736765886130e-17; // π/2 − double(π/2)
};

// atan2(y, x) lane by lane (the quadrant convention of torch.atan2 for every finite input;
// atan2(±0, ±0) = 0 or π). Range reduction: z = min(|x|,|y|)/max(|x|,|y|) ∈ [0, 1], then
// atan(z) by a polynomial (AtanPoly), then the octant and quadrant are restored.
template <class V, class T>
AMS_HD V lane_atan2(const V& y, const V& x) {
  const T pi_2 = T(1.57079632679489661923), pi_4 = T(0.78539816339744830962), pi = T(3.14159265358979323846);
  const V ax = lane_abs(x), ay = lane_abs(y);
  const auto swap = ay > ax;
  const V num = select(swap, ax, ay);
  const V den = select(swap, ay, ax);
  const V one = splat<V, T>(T(1));
  const V z = num / select(den == T(0), one, den);
  const auto big = z > AtanPoly<T>::kReduce;
  const V zr = select(big, (z - T(1)) / (z + T(1)), z);
  V r = AtanPoly<T>::atan(zr) + select(big, splat<V, T>(pi_4 + T(0.5) * T(AtanPoly<T>::kMoreBits)), splat<V, T>(T(0)));
  r = select(swap, (pi_2 - r) + T(AtanPoly<T>::kMoreBits), r);
  r = select(x < T(0), (pi - r) + T(2) * T(AtanPoly<T>::kMoreBits), r);
  return select(y < T(0), -r, r);
}

// forces.safe_normalize: unit vector and length of d (3 lanes); zero direction and length when
// |d|² <= eps (eps = 1e-20 by default, 1e-24 for the angular spring's perpendicular).
template <class V, class T>
AMS_HD void safe_normalize(const V d[3], V unit[3], V& length, T eps) {
  const V sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
  const auto nonzero = sq > eps;
  const V zero = splat<V, T>(T(0));
  const V len = LaneMath<V>::sqrt(select(nonzero, sq, splat<V, T>(T(1))));
  for (int c = 0; c < 3; ++c) unit[c] = select(nonzero, d[c] / len, zero);
  length = select(nonzero, len, zero);
}

template <class V, class T>
AMS_HD void load3(const Lanes<V, T>& a, int64_t i, V out[3]) {
  out[0] = a[3 * i + 0];
  out[1] = a[3 * i + 1];
  out[2] = a[3 * i + 2];
}

template <class V, class T>
AMS_HD void store3(const Lanes<V, T>& a, int64_t i, const V in[3]) {
  a[3 * i + 0] = in[0];
  a[3 * i + 1] = in[1];
  a[3 * i + 2] = in[2];
}

// R p + t for a row-major 3×3 R and translation t (Pose.to_world), or R p (Pose.rotate).
template <class V, class T>
AMS_HD void rigid_map(const T* R, const T* t, const V p[3], V out[3]) {
  for (int r = 0; r < 3; ++r) out[r] = (R[3 * r + 0] * p[0] + R[3 * r + 1] * p[1] + R[3 * r + 2] * p[2]) + t[r];
}

template <class V, class T>
AMS_HD void rotate(const T* R, const V p[3], V out[3]) {
  for (int r = 0; r < 3; ++r) out[r] = R[3 * r + 0] * p[0] + R[3 * r + 1] * p[1] + R[3 * r + 2] * p[2];
}

} // namespace frame
} // namespace ams_torch
