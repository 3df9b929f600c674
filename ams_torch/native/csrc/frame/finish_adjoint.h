// Adjoints of the frame's end (finish.h) and of the plastic yield of the non-Hookean integrity
// coupling (SPEC §7), written once for the host (finish_adjoint_cpu.cpp) and the device
// (finish_adjoint_cuda.cu). The definitions are ams_torch/sim/finish.py::pin_and_speed and
// ams_torch/sim/forces.py::integrity_yield, differentiated by autograd; below that derivative
// written out, with autograd's conventions: vector_norm passes nothing at a zero vector (a pinned
// particle's speed), torch.where passes the gradient to the branch it took, a comparison none.
//
// finish, per particle (h = u + ω × (x − t), v' = h if pinned else v, speed = |v' − h|), given
// the adjoints of v' and speed: r̄ = speed̄ (v' − h) / speed (0 at speed 0), v̄'ₜ = v̄' + r̄,
// h̄ = −r̄ + (pinned ? v̄'ₜ : 0), v̄ = pinned ? 0 : v̄'ₜ, x̄ = h̄ × ω, t̄ −= h̄ × ω, ū += h̄,
// ω̄ += (x − t) × h̄; the pose's adjoints summed per strand (the caller sums the strands).
//
// yield, per particle (d = a − x in the head frame, u = d / |d| (0 where |d|² <= 1e-20), limit
// L = breaking × segment length; where |d| > L and the particle is free: a' = x + L u, else a' = a),
// given ā': where it yielded x̄ = ā' − d̄, ā = d̄, L̄ = ā'·u with d̄ = (L ā' − u (u·L ā')) / |d|;
// elsewhere ā = ā'.
// No torch headers.
#pragma once

#include <math.h>
#include <stdint.h>

#include "frame/finish.h"

namespace ams_torch {
namespace frame {

// Strand g (0 <= g < B S) of the finish's adjoint: g_out (v̄'), g_speed (speed̄, or null), into
// g_x, g_v (the strand's particles) and g_pose[9] (the strand's t̄, ū, ω̄).
template <class T>
AMS_HD void finish_adjoint_strand(const FinishArgs<T>& a, int64_t g, const T* g_out, const T* g_speed, T* g_x,
                                  T* g_v, T* g_pose) {
  const int64_t b = g / a.strands, s = g - b * a.strands;
  const int64_t q = a.pose_scenes == 1 ? 0 : b;
  const T t[3] = {a.translation[3 * q], a.translation[3 * q + 1], a.translation[3 * q + 2]};
  const T u[3] = {a.linear[3 * q], a.linear[3 * q + 1], a.linear[3 * q + 2]};
  const T w[3] = {a.angular[3 * q], a.angular[3 * q + 1], a.angular[3 * q + 2]};
  const int64_t pinned = a.num_pinned[s];
  const int64_t base = g * a.particles;
  T acc[9] = {T(0), T(0), T(0), T(0), T(0), T(0), T(0), T(0), T(0)};
  for (int64_t i = 0; i < a.particles; ++i) {
    const int64_t p = base + i;
    const T* x = a.x + 3 * p;
    const T* v = a.v + 3 * p;
    const T d[3] = {x[0] - t[0], x[1] - t[1], x[2] - t[2]};
    const T h[3] = {u[0] + (w[1] * d[2] - w[2] * d[1]), u[1] + (w[2] * d[0] - w[0] * d[2]),
                    u[2] + (w[0] * d[1] - w[1] * d[0])};
    const bool pin = i < pinned;
    T o[3], r[3];
    for (int k = 0; k < 3; ++k) {
      o[k] = pin ? h[k] : v[k];
      r[k] = o[k] - h[k];
    }
    const T speed = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
    T rb[3] = {T(0), T(0), T(0)};
    if (g_speed != nullptr && speed != T(0)) {
      const T f = g_speed[p] / speed;
      for (int k = 0; k < 3; ++k) rb[k] = f * r[k];
    }
    T hb[3];
    for (int k = 0; k < 3; ++k) {
      const T ob = g_out[3 * p + k] + rb[k];
      hb[k] = pin ? ob - rb[k] : -rb[k];
      g_v[3 * p + k] = pin ? T(0) : ob;
    }
    // h = u + ω × d: d̄ = h̄ × ω, ω̄ = d × h̄
    const T db[3] = {hb[1] * w[2] - hb[2] * w[1], hb[2] * w[0] - hb[0] * w[2], hb[0] * w[1] - hb[1] * w[0]};
    const T wb[3] = {d[1] * hb[2] - d[2] * hb[1], d[2] * hb[0] - d[0] * hb[2], d[0] * hb[1] - d[1] * hb[0]};
    for (int k = 0; k < 3; ++k) {
      g_x[3 * p + k] = db[k];
      acc[k] -= db[k];
      acc[3 + k] += hb[k];
      acc[6 + k] += wb[k];
    }
  }
  for (int k = 0; k < 9; ++k) g_pose[9 * g + k] = acc[k];
}

// Particle p of the yield's adjoint: x_local, anchor, g_new (3 each), limit L, free; writes g_x,
// g_anchor (3 each) and *g_limit.
template <class T>
AMS_HD void yield_adjoint_particle(const T* x, const T* anchor, T limit, bool free, const T* g_new, T* g_x,
                                   T* g_anchor, T* g_limit) {
  const T d[3] = {anchor[0] - x[0], anchor[1] - x[1], anchor[2] - x[2]};
  const T sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
  const bool nonzero = sq > T(1e-20);
  const T len = nonzero ? sqrt(sq) : T(1);
  const T dist = nonzero ? len : T(0);
  if (!(dist > limit && free)) {
    for (int k = 0; k < 3; ++k) {
      g_x[k] = T(0);
      g_anchor[k] = g_new[k];
    }
    *g_limit = T(0);
    return;
  }
  const T unit[3] = {d[0] / len, d[1] / len, d[2] / len};
  T gu[3], dot = T(0);
  for (int k = 0; k < 3; ++k) {
    gu[k] = limit * g_new[k];
    dot = dot + unit[k] * gu[k];
  }
  *g_limit = g_new[0] * unit[0] + g_new[1] * unit[1] + g_new[2] * unit[2];
  for (int k = 0; k < 3; ++k) {
    const T gd = (gu[k] - unit[k] * dot) / len;
    g_anchor[k] = gd;
    g_x[k] = g_new[k] - gd;
  }
}

} // namespace frame
} // namespace ams_torch
