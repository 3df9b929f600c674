// The end of a frame (SPEC §4, the step's last stage before the plastic yield), one particle at a
// time, written once for the host (frame_cpu.cpp) and the device (frame_cuda.cu). The torch
// definition is ams_torch/sim/finish.py::pin_and_speed:
//
//   h = u + ω × (x − t)            the head's rigid velocity at the particle (Pose.velocity_at)
//   v' = h if pinned, else v       pinned particles move with the head
//   speed = |v' − h|               the speed relative to the head (the divergence flag's input)
//
// in the same order as torch (cross product, then the sum; the difference, then the 2-norm), so
// float64 results agree to rounding. NaN/Inf in x, v or the pose give a NaN/Inf speed.
#pragma once

#include <math.h>
#include <stdint.h>

#include "banded_cholesky.h"

namespace ams_torch {
namespace frame {

// Raw pointers of one call: x, v (B, S, N, 3); num_pinned (S,); translation, linear and angular
// velocity (P, 3) with P = 1 or B (pose_scenes); outputs v' (B, S, N, 3) and speed (B, S, N).
template <class T>
struct FinishArgs {
  int64_t scenes, strands, particles, pose_scenes;
  const T *x, *v, *translation, *linear, *angular;
  const int64_t* num_pinned;
  T *v_out, *speed;
};

// Particle p (0 <= p < B S N, the flat index of (b, s, i)).
template <class T>
AMS_HD void finish_particle(const FinishArgs<T>& a, int64_t p) {
  const int64_t strand = p / a.particles, i = p - strand * a.particles;
  const int64_t b = strand / a.strands, s = strand - b * a.strands;
  const int64_t q = a.pose_scenes == 1 ? 0 : b;
  const T* t = a.translation + 3 * q;
  const T* u = a.linear + 3 * q;
  const T* w = a.angular + 3 * q;
  const T* x = a.x + 3 * p;
  const T* v = a.v + 3 * p;
  const T d0 = x[0] - t[0], d1 = x[1] - t[1], d2 = x[2] - t[2];
  const T h0 = u[0] + (w[1] * d2 - w[2] * d1);
  const T h1 = u[1] + (w[2] * d0 - w[0] * d2);
  const T h2 = u[2] + (w[0] * d1 - w[1] * d0);
  const bool pinned = i < a.num_pinned[s];
  const T o0 = pinned ? h0 : v[0], o1 = pinned ? h1 : v[1], o2 = pinned ? h2 : v[2];
  T* out = a.v_out + 3 * p;
  out[0] = o0;
  out[1] = o1;
  out[2] = o2;
  const T r0 = o0 - h0, r1 = o1 - h1, r2 = o2 - h2;
  a.speed[p] = sqrt(r0 * r0 + r1 * r1 + r2 * r2);
}

} // namespace frame
} // namespace ams_torch
