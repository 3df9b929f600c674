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

#include "banded/banded_cholesky.h"

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

// Particles [i0, i1) of strand g (0 <= g < B S, the flat index of (b, s)): the pose and pinned
// count are read once, the loop over particles has no index arithmetic (the CPU kernel runs it
// over whole strands, where the compiler vectorises it).
template <class T>
AMS_HD void finish_range(const FinishArgs<T>& a, int64_t g, int64_t i0, int64_t i1) {
  const int64_t b = g / a.strands, s = g - b * a.strands;
  const int64_t q = a.pose_scenes == 1 ? 0 : b;
  const T t0 = a.translation[3 * q], t1 = a.translation[3 * q + 1], t2 = a.translation[3 * q + 2];
  const T u0 = a.linear[3 * q], u1 = a.linear[3 * q + 1], u2 = a.linear[3 * q + 2];
  const T w0 = a.angular[3 * q], w1 = a.angular[3 * q + 1], w2 = a.angular[3 * q + 2];
  const int64_t pinned = a.num_pinned[s];
  const int64_t base = g * a.particles;
  const T* x = a.x + 3 * base;
  const T* v = a.v + 3 * base;
  T* out = a.v_out + 3 * base;
  T* speed = a.speed + base;
  for (int64_t i = i0; i < i1; ++i) {
    const T d0 = x[3 * i] - t0, d1 = x[3 * i + 1] - t1, d2 = x[3 * i + 2] - t2;
    const T h0 = u0 + (w1 * d2 - w2 * d1);
    const T h1 = u1 + (w2 * d0 - w0 * d2);
    const T h2 = u2 + (w0 * d1 - w1 * d0);
    const bool pin = i < pinned;
    const T o0 = pin ? h0 : v[3 * i], o1 = pin ? h1 : v[3 * i + 1], o2 = pin ? h2 : v[3 * i + 2];
    out[3 * i] = o0;
    out[3 * i + 1] = o1;
    out[3 * i + 2] = o2;
    const T r0 = o0 - h0, r1 = o1 - h1, r2 = o2 - h2;
    speed[i] = sqrt(r0 * r0 + r1 * r1 + r2 * r2);
  }
}

// Particle p (0 <= p < B S N, the flat index of (b, s, i)): one thread of the CUDA kernel.
template <class T>
AMS_HD void finish_particle(const FinishArgs<T>& a, int64_t p) {
  const int64_t g = p / a.particles;
  const int64_t i = p - g * a.particles;
  finish_range(a, g, i, i + 1);
}

} // namespace frame
} // namespace ams_torch
