// The collision stage of one strand (or W strands in lock-step), written once for the host (CPU
// kernel, collide_cpu.cpp) and the device (CUDA kernel, collide_cuda.cu). The torch definition is
// ams_torch/sim/step.py::collisions: the contact response of every collider in order
// (ams_torch/stages/collide/response.py::collide), then `rounds` rounds of follow-the-leader
// (frame/ftl.h, the same routine as the fused frame) and push-out (the response with Δt = 0).
// Same arithmetic, same order, same branches (torch.where) as the torch code:
//
//   per particle i (free: i >= the strand's pinned count), per collider c in order:
//     local p = Rᵀ(x − t)  (as x R − t R);  σ, n_local = distance_and_normal(p);  n = R n_local
//     inside = σ < 0 and free
//     v' = contact_response(v, v_c = lin + ω × (x − t), n, μ);  x' = x + Δt (v' − v)
//     `iterations` push-out passes: x' += max(−σ(x'), 0) R n_local(x')
//     x, v = inside ? (x', v') : (x, v)
//
// Shapes: sphere (center, radius), capsule (a, b, radius), plane (point, unit normal), hollow
// sphere (center, frame rows e1/axis/e2, radius, thickness, cut height; exact σ as
// HollowSphereCollider) and mesh (SDFGrid: trilinear samples of the 4-channel volume (σ, ∇σ)
// with grid_sample's bilinear/border/align_corners=True arithmetic, corner by corner in its
// order, plus the outside-the-box correction of SDFGrid.distance_and_normal).
#pragma once

#include <math.h>
#include <stdint.h>

#include <type_traits>

#include "frame/ftl.h"
#include "frame/lanes.h"

namespace ams_torch {
namespace collide {

using frame::lane_max;
using frame::lane_min;
using frame::LaneMath;
using frame::Lanes;
using frame::select;
using frame::splat;

enum ColliderType { kSphere = 0, kCapsule = 1, kPlane = 2, kHollowSphere = 3, kMesh = 4, kColliderTypes = 5 };
constexpr int kMaxColliders = 16;

// One collider as given to the kernel (device pointers on CUDA). Geometry tensors g0..g2 and
// numbers f[0..2] by type:
//   sphere: g0 center (3);  f radius
//   capsule: g0 a (3), g1 b (3);  f radius
//   plane: g0 point (3), g1 unit normal (3)
//   hollow sphere: g0 center (3), g1 frame (3, 3) rows (e1, axis, e2);  f radius, thickness,
//                  cut height (NaN: closed shell)
//   mesh: g0 volume (nz, ny, nx, 4) (σ, ∂σ/∂x, ∂σ/∂y, ∂σ/∂z last: one sample's four values share a
//         cache line), g1 box lower corner (3), g2 upper (3)
// The pose (R (P, 3, 3), t, lin, ω (P, 3)) is the collider's world pose at the end of the frame,
// P = 1 or one per scene; without velocity the collider is static.
template <class T>
struct ColliderArgs {
  int type, iterations, has_velocity;
  int64_t pose_scenes;
  const T* rotation;
  const T* translation;
  const T* linear_velocity;
  const T* angular_velocity;
  const T* friction;
  const T* g0;
  const T* g1;
  const T* g2;
  double f[3];
  int64_t nx, ny, nz;
};

template <class T>
struct CollideArgs {
  int64_t scenes, strands, particles; // B, S, N
  const T* x;                         // (B, S, N, 3)
  const T* v;
  const T* rest_positions;   // (S, N, 3)
  const T* edge_rest_length; // (S, N − 1)
  const int64_t* num_pinned; // (S,)
  const T* head_rotation;    // (P_h, 3, 3), P_h = 1 or B: follow-the-leader's fallback directions
  int64_t head_scenes;
  int count;
  ColliderArgs<T> colliders[kMaxColliders];
};

struct CollideSettings {
  double dt;        // frame length, s (the response's Δt; push-out rounds use 0)
  int rounds;       // config.collision_rounds
  bool inextensibility;
  double ftl_damping;
};

// A collider's values for one scene, read once (scalars shared by every lane).
template <class T>
struct Prepared {
  int type, iterations, has_velocity;
  T R[9], t[3], offset[3], lin[3], ang[3], mu;
  T a[3], b[3], ab[3], abab; // sphere/hollow: a = center; capsule: a, b, b − a, max(|ab|², 1e-30); plane: a = point, b = normal
  T frame[9], radius, half, cut, rim; // hollow sphere (rim = √(radius² − cut²))
  int has_cut;
  const T* volume; // mesh
  int64_t nx, ny, nz;
  T bias[3], scale[3];
};

template <class T>
AMS_HD void prepare_collider(const ColliderArgs<T>& c, int64_t scene, Prepared<T>& p) {
  p.type = c.type;
  p.iterations = c.iterations > 1 ? c.iterations : 1;
  p.has_velocity = c.has_velocity;
  const int64_t k = c.pose_scenes == 1 ? 0 : scene;
  for (int e = 0; e < 9; ++e) p.R[e] = c.rotation[9 * k + e];
  for (int q = 0; q < 3; ++q) {
    p.t[q] = c.translation[3 * k + q];
    p.lin[q] = c.has_velocity ? c.linear_velocity[3 * k + q] : T(0);
    p.ang[q] = c.has_velocity ? c.angular_velocity[3 * k + q] : T(0);
  }
  for (int j = 0; j < 3; ++j) p.offset[j] = -(p.t[0] * p.R[j] + p.t[1] * p.R[3 + j] + p.t[2] * p.R[6 + j]);
  p.mu = *c.friction;
  p.volume = nullptr;
  p.nx = p.ny = p.nz = 0;
  p.has_cut = 0;
  switch (c.type) {
    case kSphere:
    case kHollowSphere:
      for (int q = 0; q < 3; ++q) p.a[q] = c.g0[q];
      p.radius = T(c.f[0]);
      if (c.type == kHollowSphere) {
        for (int e = 0; e < 9; ++e) p.frame[e] = c.g1[e];
        p.half = T(0.5 * c.f[1]);
        p.has_cut = c.f[2] == c.f[2]; // not NaN
        p.cut = p.has_cut ? T(c.f[2]) : T(0);
        p.rim = p.has_cut ? T(sqrt(c.f[0] * c.f[0] - c.f[2] * c.f[2])) : T(0);
      }
      break;
    case kCapsule:
      for (int q = 0; q < 3; ++q) {
        p.a[q] = c.g0[q];
        p.b[q] = c.g1[q];
        p.ab[q] = p.b[q] - p.a[q];
      }
      p.abab = p.ab[0] * p.ab[0] + p.ab[1] * p.ab[1] + p.ab[2] * p.ab[2];
      p.abab = p.abab < T(1e-30) ? T(1e-30) : p.abab;
      p.radius = T(c.f[0]);
      break;
    case kPlane:
      for (int q = 0; q < 3; ++q) {
        p.a[q] = c.g0[q];
        p.b[q] = c.g1[q];
      }
      break;
    default: // mesh: SDFGrid._prepare's map from metres to grid_sample's [−1, 1]
      p.volume = c.g0;
      p.nx = c.nx;
      p.ny = c.ny;
      p.nz = c.nz;
      for (int q = 0; q < 3; ++q) {
        const T lo = c.g1[q], hi = c.g2[q];
        p.scale[q] = T(2) / (hi - lo);
        p.bias[q] = T(-1) - lo * p.scale[q];
      }
      break;
  }
}

// ---------------------------------------------------------------------------------------
// lane access (scalar: one lane; GCC vectors: W lanes), for the mesh grid's gathers
// ---------------------------------------------------------------------------------------

template <class V, class T>
struct LaneAccess {
  static constexpr int kWidth = int(sizeof(V) / sizeof(T));
  static AMS_HD T get(const V& v, int l) { return v[l]; }
  static AMS_HD void set(V& v, int l, T x) { v[l] = x; }
};

template <class T>
struct LaneAccess<T, T> {
  static constexpr int kWidth = 1;
  static AMS_HD T get(const T& v, int) { return v; }
  static AMS_HD void set(T& v, int, T x) { v = x; }
};

template <class T>
AMS_HD T scalar_floor(T x) {
  return ::floor(x);
}
template <>
AMS_HD float scalar_floor<float>(float x) {
  return ::floorf(x);
}

template <class V, class T>
AMS_HD V lane_floor(const V& x) {
  using L = LaneAccess<V, T>;
  V r = x;
  for (int l = 0; l < L::kWidth; ++l) L::set(r, l, scalar_floor(L::get(x, l)));
  return r;
}

// (σ, ∇σ) at continuous grid coordinates (ix, iy, iz) ∈ [0, n − 1]³ (already clipped), as
// grid_sample's trilinear kernel: eight corners tnw, tne, tsw, tse, bnw, bne, bsw, bse in its
// order, each added only when inside the grid (with border clipping only the +1 corners of a
// coordinate exactly on the last sample fall outside, where their weight is 0).
template <class V, class T>
AMS_HD void trilinear4(const Prepared<T>& c, const V& ix, const V& iy, const V& iz, V out[4]) {
  using L = LaneAccess<V, T>;
  const V x0 = lane_floor<V, T>(ix), y0 = lane_floor<V, T>(iy), z0 = lane_floor<V, T>(iz);
  const V x1 = x0 + T(1), y1 = y0 + T(1), z1 = z0 + T(1);
  const V wx[2] = {x1 - ix, ix - x0}, wy[2] = {y1 - iy, iy - y0}, wz[2] = {z1 - iz, iz - z0};
  const V cx[2] = {x0, x1}, cy[2] = {y0, y1}, cz[2] = {z0, z1};
  const V zero = splat<V, T>(T(0));
  for (int ch = 0; ch < 4; ++ch) out[ch] = zero;
  const int64_t plane = c.nx * c.ny;
  for (int corner = 0; corner < 8; ++corner) { // bit 0: x + 1, bit 1: y + 1, bit 2: z + 1
    const int bx = corner & 1, by = (corner >> 1) & 1, bz = (corner >> 2) & 1;
    const V w = wx[bx] * wy[by] * wz[bz];
    const auto inb = (cx[bx] < T(c.nx)) & (cy[by] < T(c.ny)) & (cz[bz] < T(c.nz));
    V val[4] = {zero, zero, zero, zero};
    for (int l = 0; l < L::kWidth; ++l) {
      int64_t xi = int64_t(L::get(cx[bx], l)), yi = int64_t(L::get(cy[by], l)), zi = int64_t(L::get(cz[bz], l));
      xi = xi < c.nx - 1 ? xi : c.nx - 1;
      yi = yi < c.ny - 1 ? yi : c.ny - 1;
      zi = zi < c.nz - 1 ? zi : c.nz - 1;
      const int64_t at = zi * plane + yi * c.nx + xi;
      for (int ch = 0; ch < 4; ++ch) L::set(val[ch], l, c.volume[4 * at + ch]);
    }
    for (int ch = 0; ch < 4; ++ch) out[ch] = select(inb, out[ch] + val[ch] * w, out[ch]);
  }
}

// grid_sample's unnormalise (align_corners=True) and border clip: [−1, 1] → [0, size − 1].
template <class V, class T>
AMS_HD V grid_coordinate(const V& coord, int64_t size) {
  const V s = ((coord + T(1)) / T(2)) * T(size - 1);
  return lane_min(splat<V, T>(T(size - 1)), lane_max(s, splat<V, T>(T(0))));
}

template <class V>
AMS_HD V dot3(const V a[3], const V b[3]) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

template <class V, class T>
AMS_HD V norm3(const V a[3]) {
  return LaneMath<V>::sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
}

// shapes._unit_or: (d/|d|, |d|) with `fallback` where |d| = 0.
template <class V, class T>
AMS_HD V unit_or(const V d[3], const T fallback[3], V unit[3]) {
  const V len = norm3<V, T>(d);
  const V safe = lane_max(len, splat<V, T>(T(1e-30)));
  const auto positive = len > T(0);
  for (int q = 0; q < 3; ++q) unit[q] = select(positive, d[q] / safe, splat<V, T>(fallback[q]));
  return len;
}

// σ (metres, negative inside) and the unit outward normal at local points p.
template <class V, class T>
AMS_HD void distance_and_normal(const Prepared<T>& c, const V p[3], V& sigma, V n[3]) {
  const T up[3] = {T(0), T(1), T(0)};
  switch (c.type) {
    case kSphere: {
      V d[3];
      for (int q = 0; q < 3; ++q) d[q] = p[q] - c.a[q];
      sigma = unit_or<V, T>(d, up, n) - c.radius;
      return;
    }
    case kCapsule: {
      V pa[3], d[3];
      for (int q = 0; q < 3; ++q) pa[q] = p[q] - c.a[q];
      const V h = lane_min(lane_max((pa[0] * c.ab[0] + pa[1] * c.ab[1] + pa[2] * c.ab[2]) / c.abab,
                                    splat<V, T>(T(0))), splat<V, T>(T(1)));
      for (int q = 0; q < 3; ++q) d[q] = pa[q] - h * c.ab[q];
      sigma = unit_or<V, T>(d, up, n) - c.radius;
      return;
    }
    case kPlane: {
      sigma = (p[0] - c.a[0]) * c.b[0] + (p[1] - c.a[1]) * c.b[1] + (p[2] - c.a[2]) * c.b[2];
      for (int q = 0; q < 3; ++q) n[q] = splat<V, T>(c.b[q]);
      return;
    }
    case kHollowSphere: {
      V d[3], q[3], radial[3], nq[3];
      for (int j = 0; j < 3; ++j) d[j] = p[j] - c.a[j];
      for (int r = 0; r < 3; ++r) q[r] = d[0] * c.frame[3 * r + 0] + d[1] * c.frame[3 * r + 1] + d[2] * c.frame[3 * r + 2];
      const V dist_c = unit_or<V, T>(q, up, radial);
      const V sign = select(dist_c >= c.radius, splat<V, T>(T(1)), splat<V, T>(T(-1)));
      const V off = dist_c - c.radius;
      sigma = select(off < T(0), -off, off) - c.half;
      for (int r = 0; r < 3; ++r) nq[r] = sign * radial[r];
      if (c.has_cut) {
        const V rho = LaneMath<V>::sqrt(q[0] * q[0] + q[2] * q[2]);
        const auto rim = c.cut * rho < c.rim * q[1];
        const T ex[3] = {T(1), T(0), T(0)};
        const V zero = splat<V, T>(T(0));
        V flat[3] = {q[0], zero, q[2]}, horiz[3];
        unit_or<V, T>(flat, ex, horiz);
        const V tr0 = rho - c.rim, tr1 = q[1] - c.cut;
        const V rim_dist = LaneMath<V>::sqrt(tr0 * tr0 + tr1 * tr1);
        const V safe = lane_max(rim_dist, splat<V, T>(T(1e-30)));
        const V rd0 = tr0 / safe, rd1 = tr1 / safe;
        const auto positive = rim_dist > T(0);
        for (int r = 0; r < 3; ++r) {
          const V rim_n = select(positive, rd0 * horiz[r] + rd1 * up[r], splat<V, T>(up[r]));
          nq[r] = select(rim, rim_n, nq[r]);
        }
        sigma = select(rim, rim_dist - c.half, sigma);
      }
      for (int j = 0; j < 3; ++j) n[j] = nq[0] * c.frame[j] + nq[1] * c.frame[3 + j] + nq[2] * c.frame[6 + j];
      return;
    }
    default: { // mesh (SDFGrid.distance_and_normal)
      V coord[3], outside[3];
      for (int q = 0; q < 3; ++q) {
        const V raw = c.bias[q] + p[q] * c.scale[q];
        coord[q] = lane_min(lane_max(raw, splat<V, T>(T(-1))), splat<V, T>(T(1)));
        outside[q] = (raw - coord[q]) / c.scale[q];
      }
      V s[4];
      trilinear4<V, T>(c, grid_coordinate<V, T>(coord[0], c.nx), grid_coordinate<V, T>(coord[1], c.ny),
                       grid_coordinate<V, T>(coord[2], c.nz), s);
      const V dist_out = norm3<V, T>(outside);
      sigma = s[0] + dist_out;
      const V safe_out = lane_max(dist_out, splat<V, T>(T(1e-30)));
      V grad[3];
      for (int q = 0; q < 3; ++q) grad[q] = s[1 + q] + outside[q] / safe_out;
      const V gn = norm3<V, T>(grad);
      const V safe_g = lane_max(gn, splat<V, T>(T(1e-12)));
      const auto ok = gn > T(1e-12);
      for (int q = 0; q < 3; ++q) n[q] = select(ok, grad[q] / safe_g, splat<V, T>(up[q]));
      return;
    }
  }
}

// Culling (exact): whether σ ≥ 0 holds in every lane at local points p of a mesh collider, read
// from the 8 σ samples around each point (those trilinear4 weighs, indices clamped alike). The
// trilinear value is a sum of non-negative weights times those samples (plus a distance ≥ 0
// outside the box), so it is ≥ 0 where every sample is; no lane is then inside and `respond`
// would change nothing. 8 values per lane instead of 32, for the many particles far from a mesh.
template <class V, class T>
AMS_HD bool mesh_surely_outside(const Prepared<T>& c, const V p[3]) {
  using L = LaneAccess<V, T>;
  V g[3];
  const int64_t size[3] = {c.nx, c.ny, c.nz};
  for (int q = 0; q < 3; ++q) {
    const V raw = c.bias[q] + p[q] * c.scale[q];
    g[q] = grid_coordinate<V, T>(lane_min(lane_max(raw, splat<V, T>(T(-1))), splat<V, T>(T(1))), size[q]);
  }
  const int64_t plane = c.nx * c.ny;
  for (int l = 0; l < L::kWidth; ++l) {
    int64_t lo[3], hi[3];
    for (int q = 0; q < 3; ++q) {
      const int64_t i0 = int64_t(scalar_floor(L::get(g[q], l)));
      lo[q] = i0 < size[q] - 1 ? i0 : size[q] - 1;
      hi[q] = i0 + 1 < size[q] - 1 ? i0 + 1 : size[q] - 1;
    }
    for (int corner = 0; corner < 8; ++corner) {
      const int64_t xi = corner & 1 ? hi[0] : lo[0], yi = (corner >> 1) & 1 ? hi[1] : lo[1],
                    zi = (corner >> 2) & 1 ? hi[2] : lo[2];
      if (!(c.volume[4 * (zi * plane + yi * c.nx + xi)] >= T(0))) return false;
    }
  }
  return true;
}

// response.contact_response: Coulomb response for particles in contact.
template <class V, class T>
AMS_HD void contact_response(const V v[3], const V vc[3], const V n[3], T mu, V out[3]) {
  V vrel[3], vt[3];
  for (int q = 0; q < 3; ++q) vrel[q] = v[q] - vc[q];
  const V vn = dot3(vrel, n);
  for (int q = 0; q < 3; ++q) vt[q] = vrel[q] - vn * n[q];
  const V vt_len = norm3<V, T>(vt);
  const V zero = splat<V, T>(T(0));
  const V dvn = lane_max(-vn, zero);
  V keep = lane_max(T(1) - mu * dvn / lane_max(vt_len, splat<V, T>(T(1e-30))), zero);
  keep = select(vt_len > T(0), keep, zero);
  const V vn_out = lane_max(vn, zero);
  for (int q = 0; q < 3; ++q) out[q] = vc[q] + vn_out * n[q] + keep * vt[q];
}

template <class V, class T>
AMS_HD void to_local(const Prepared<T>& c, const V x[3], V out[3]) {
  for (int j = 0; j < 3; ++j) out[j] = (x[0] * c.R[j] + x[1] * c.R[3 + j] + x[2] * c.R[6 + j]) + c.offset[j];
}

template <class V, class T>
AMS_HD void rotate_normal(const Prepared<T>& c, const V nl[3], V out[3]) {
  for (int r = 0; r < 3; ++r) out[r] = nl[0] * c.R[3 * r] + nl[1] * c.R[3 * r + 1] + nl[2] * c.R[3 * r + 2];
}

// Whether any lane of a mask is set (a comparison of scalars gives an integer, of vectors an
// integer vector).
template <class M>
AMS_HD bool any_lane(const M& m) {
  if constexpr (std::is_integral<M>::value) {
    return m != 0;
  } else {
    for (int l = 0; l < int(sizeof(M) / sizeof(m[0])); ++l)
      if (m[l]) return true;
    return false;
  }
}

// One collider's response on one particle (collide's loop body); x, v updated in place. The
// torch definition computes the response and the push-out everywhere and keeps them where the
// particle is inside; here they are skipped when no lane is inside (the same values are kept).
template <class V, class T, class M>
AMS_HD void respond(const Prepared<T>& c, T dt, const M& free, V x[3], V v[3]) {
  V local[3], nl[3], n[3], sigma;
  to_local(c, x, local);
  if (c.type == kMesh && mesh_surely_outside<V, T>(c, local)) return; // no lane inside: nothing changes
  distance_and_normal<V, T>(c, local, sigma, nl);
  const auto inside = (sigma < T(0)) & free;
  if (!any_lane(inside)) return;
  rotate_normal(c, nl, n);
  V vc[3];
  const V zero = splat<V, T>(T(0));
  if (c.has_velocity) {
    V r[3];
    for (int q = 0; q < 3; ++q) r[q] = x[q] - c.t[q];
    vc[0] = c.lin[0] + (c.ang[1] * r[2] - c.ang[2] * r[1]);
    vc[1] = c.lin[1] + (c.ang[2] * r[0] - c.ang[0] * r[2]);
    vc[2] = c.lin[2] + (c.ang[0] * r[1] - c.ang[1] * r[0]);
  } else {
    vc[0] = vc[1] = vc[2] = zero;
  }
  V vn[3], xn[3];
  contact_response<V, T>(v, vc, n, c.mu, vn);
  for (int q = 0; q < 3; ++q) xn[q] = x[q] + dt * (vn[q] - v[q]);
  for (int it = 0; it < c.iterations; ++it) {
    V l2[3], n2l[3], n2[3], s2;
    to_local(c, xn, l2);
    distance_and_normal<V, T>(c, l2, s2, n2l);
    const V depth = lane_max(-s2, zero);
    rotate_normal(c, n2l, n2);
    for (int q = 0; q < 3; ++q) xn[q] = xn[q] + depth * n2[q];
  }
  for (int q = 0; q < 3; ++q) {
    x[q] = select(inside, xn[q], x[q]);
    v[q] = select(inside, vn[q], v[q]);
  }
}

// collide(x, v, dt, colliders, poses, free) for one strand: every collider on every particle.
template <class V, class T>
AMS_HD void collide_strand(const Lanes<V, T>& x, const Lanes<V, T>& v, int64_t n, const V& pinned,
                           const Prepared<T>* colliders, int count, T dt) {
  for (int64_t i = 0; i < n; ++i) {
    V xi[3], vi[3];
    frame::load3(x, i, xi);
    frame::load3(v, i, vi);
    const auto free = T(i) >= pinned;
    for (int c = 0; c < count; ++c) respond<V, T>(colliders[c], dt, free, xi, vi);
    frame::store3(x, i, xi);
    frame::store3(v, i, vi);
  }
}

// The whole stage for one strand (step.collisions): response at Δt, then `rounds` rounds of
// follow-the-leader (head rotation R_head) and push-out at Δt = 0, when inextensibility is on.
template <class V, class T>
AMS_HD void collision_stage(const Lanes<V, T>& x, const Lanes<V, T>& v, const Lanes<V, T>& rest,
                            const Lanes<V, T>& edge_length, int64_t n, const V& pinned, const Prepared<T>* colliders,
                            int count, const CollideSettings& cfg, const T* head_rotation) {
  collide_strand(x, v, n, pinned, colliders, count, T(cfg.dt));
  if (!cfg.inextensibility) return;
  for (int r = 0; r < cfg.rounds; ++r) {
    frame::follow_the_leader(x, v, rest, edge_length, pinned, head_rotation, T(cfg.ftl_damping), T(cfg.dt), n);
    collide_strand(x, v, n, pinned, colliders, count, T(0));
  }
}

} // namespace collide
} // namespace ams_torch
