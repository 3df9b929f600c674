// Follow-the-leader inextensibility of one strand (or W strands in lock-step), host and device:
// the arithmetic of ams_torch/sim/inextensibility.py::follow_the_leader with the fallback
// directions of ams_torch/sim/dynamics.py::inextensibility (the rest edges carried by the head's
// rotation). Shared by the fused frame kernel (frame.h) and the collision stage.
#pragma once

#include "frame/lanes.h"

namespace ams_torch {
namespace frame {

// Müller et al. 2012 DFTL, root to tip, in place on x and v (N rows of 3):
//   d_i  = safe_normalize(x_i − p_{i−1}), or the fallback R (X̄_i − X̄_{i−1}) normalised where the
//          edge has collapsed (|d|² <= 1e-20);
//   p_i  = x_i for pinned i, else p_{i−1} + l_{i−1} d_i;   c_i = p_i − x_i  (c_0 = 0);
//   v_i += (c_i − damping c_{i+1}) / dt on free particles (c_N = 0); x_i = p_i.
// rest: rest positions (N rows of 3, head frame); edge_length: N−1 rest lengths; R: row-major
// head rotation at the end of the frame; pinned: the number of pinned particles (per lane, as a
// value of T), pinned_max: its maximum over the lanes.
template <class V, class T>
AMS_HD void follow_the_leader(const Lanes<V, T>& x, const Lanes<V, T>& v, const Lanes<V, T>& rest,
                              const Lanes<V, T>& edge_length, const V& pinned, const T* R, T damping, T dt,
                              int64_t n) {
  const V zero = splat<V, T>(T(0));
  V prev[3], corr_prev[3] = {zero, zero, zero};
  load3(x, 0, prev);
  for (int64_t i = 1; i < n; ++i) {
    V xi[3], d[3], unit[3], len;
    load3(x, i, xi);
    for (int c = 0; c < 3; ++c) d[c] = xi[c] - prev[c];
    safe_normalize(d, unit, len, T(1e-20));
    V r1[3], r0[3], rd[3], rw[3], fb[3], fb_len;
    load3(rest, i, r1);
    load3(rest, i - 1, r0);
    for (int c = 0; c < 3; ++c) rd[c] = r1[c] - r0[c];
    rotate(R, rd, rw);
    safe_normalize(rw, fb, fb_len, T(1e-20));
    const V l = edge_length[i - 1];
    const auto pin_i = T(i) < pinned;
    V corr[3];
    for (int c = 0; c < 3; ++c) {
      const V dir = select(len > T(0), unit[c], fb[c]);
      const V led = prev[c] + l * dir;
      const V nw = select(pin_i, xi[c], led);
      corr[c] = nw - xi[c];
      x[3 * i + c] = nw;
      prev[c] = nw;
    }
    // particle i − 1 now has both corrections
    const auto free_prev = T(i - 1) >= pinned;
    for (int c = 0; c < 3; ++c) {
      const V vi = v[3 * (i - 1) + c];
      v[3 * (i - 1) + c] = select(free_prev, vi + (corr_prev[c] - damping * corr[c]) / dt, vi);
      corr_prev[c] = corr[c];
    }
  }
  const auto free_last = T(n - 1) >= pinned;
  for (int c = 0; c < 3; ++c) {
    const V vi = v[3 * (n - 1) + c];
    v[3 * (n - 1) + c] = select(free_last, vi + (corr_prev[c] - damping * zero) / dt, vi);
  }
}

} // namespace frame
} // namespace ams_torch
