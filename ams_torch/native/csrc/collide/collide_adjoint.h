// The adjoint (vector-Jacobian product) of the collision stage (collide.h), per strand, written
// once for the host (collide_adjoint_cpu.cpp: W strands in SIMD lanes) and the device
// (collide_adjoint_cuda.cu: one thread per strand). The definition it differentiates is the torch
// one (ams_torch/sim/contact.py::collisions_world with stages/collide/response.py and the
// colliders' distance_and_normal); its gradients equal torch autograd's to rounding
// (tests/test_grad_collisions_native.py).
//
// Recompute, then reverse (nothing kept between the passes): the stage's sub-stages are
//   0: the response of every collider at Δt;  for each round r: 2r + 1: follow-the-leader,
//   2r + 2: the response at Δt = 0 (push-out);
// the adjoint runs them again keeping the input of each (x, v: 6 N values per strand and
// sub-stage), then walks back: follow-the-leader by frame_adjoint.h's ftl_adjoint (its fallback
// directions' adjoint reaches the head rotation), the response particle by particle
// (`respond_adjoint`: the colliders' chain recomputed, then reversed collider by collider).
//
// Differentiated: x, v; each collider's world pose (R row-major, t, linear and angular velocity)
// and friction μ; the head rotation (follow-the-leader's fallback). Not differentiated (the torch
// side keeps the torch definition when they require grad): the colliders' geometry, the rest
// shape and edge lengths. Hollow spheres have no adjoint here (the torch definition runs), nor do
// more than kMaxPushout push-out passes.
//
// The conventions of the torch definition that the adjoint reproduces: clamp / clamp_min pass the
// gradient at their bounds (inclusive); norm and _safe_length have a zero gradient at zero;
// `inside` (σ < 0 and free) selects, it carries no gradient; the mesh's trilinear sample is
// differentiated as the mosaic of z-slices (sdf.py::_trilinear): x and y on the cell of floor(i)
// with the border replicated (zero slope at the last sample), z on the cell of min(floor(i), n − 2).
#pragma once

#include <math.h>
#include <stdint.h>

#include "collide/collide.h"
#include "frame/frame_adjoint.h"

namespace ams_torch {
namespace collide {

constexpr int kMaxPushout = 16; // push-out passes the adjoint keeps (more: the torch definition)
constexpr int kPoseGrads = 19;  // per collider: R̄ (9, row-major), t̄ (3), linear (3), angular (3), μ̄ (1)

// ∂(σ, ∇σ channels)/∂(ix, iy, iz) of the mesh volume at grid coordinates of one lane (see above).
template <class T>
AMS_HD void trilinear4_slope(const Prepared<T>& c, T ix, T iy, T iz, T d[4][3]) {
  const int64_t nx = c.nx, ny = c.ny, nz = c.nz;
  int64_t x0 = int64_t(scalar_floor(ix)), y0 = int64_t(scalar_floor(iy)), z0 = int64_t(scalar_floor(iz));
  x0 = x0 < 0 ? 0 : (x0 > nx - 1 ? nx - 1 : x0);
  y0 = y0 < 0 ? 0 : (y0 > ny - 1 ? ny - 1 : y0);
  z0 = z0 < 0 ? 0 : (z0 > nz - 2 ? nz - 2 : z0);
  const int64_t x1 = x0 + 1 < nx ? x0 + 1 : nx - 1, y1 = y0 + 1 < ny ? y0 + 1 : ny - 1, z1 = z0 + 1;
  const T tx = ix - T(x0), ty = iy - T(y0), tz = iz - T(z0);
  const T wx[2] = {T(1) - tx, tx}, wy[2] = {T(1) - ty, ty}, wz[2] = {T(1) - tz, tz};
  const int64_t xs[2] = {x0, x1}, ys[2] = {y0, y1}, zs[2] = {z0, z1};
  const int64_t plane = nx * ny;
  for (int ch = 0; ch < 4; ++ch) d[ch][0] = d[ch][1] = d[ch][2] = T(0);
  for (int corner = 0; corner < 8; ++corner) {
    const int bx = corner & 1, by = (corner >> 1) & 1, bz = (corner >> 2) & 1;
    const T* val = c.volume + 4 * (zs[bz] * plane + ys[by] * nx + xs[bx]);
    const T sx = bx ? T(1) : T(-1), sy = by ? T(1) : T(-1), sz = bz ? T(1) : T(-1);
    const T gx = sx * wy[by] * wz[bz], gy = sy * wx[bx] * wz[bz], gz = sz * wx[bx] * wy[by];
    for (int ch = 0; ch < 4; ++ch) {
      d[ch][0] += gx * val[ch];
      d[ch][1] += gy * val[ch];
      d[ch][2] += gz * val[ch];
    }
  }
  if (x0 == x1) d[0][0] = d[1][0] = d[2][0] = d[3][0] = T(0); // replicated border: flat
  if (y0 == y1) d[0][1] = d[1][1] = d[2][1] = d[3][1] = T(0);
}

// Adjoint of shapes._unit_or followed by σ = |d| − r: given σ̄ and n̄, d̄.
template <class V, class T>
AMS_HD void unit_or_adjoint(const V d[3], const V& sbar, const V nbar[3], V dbar[3]) {
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  const V len = norm3<V, T>(d);
  const auto positive = len > T(0);
  const V lc = lane_max(len, splat<V, T>(T(1e-30)));
  const V lcb = select(positive, -dot3(nbar, d) / (lc * lc), zero);
  const V lb = sbar + select(len >= T(1e-30), lcb, zero);
  const V per = select(positive, lb / select(positive, len, one), zero);
  for (int q = 0; q < 3; ++q) dbar[q] = select(positive, nbar[q] / lc, zero) + per * d[q];
}

// Adjoint of distance_and_normal at local points p: given σ̄ and the local normal's n̄, p̄.
template <class V, class T>
AMS_HD void distance_and_normal_adjoint(const Prepared<T>& c, const V p[3], const V& sbar, const V nbar[3],
                                        V pbar[3]) {
  using L = LaneAccess<V, T>;
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  switch (c.type) {
    case kSphere:
    case kCapsule: {
      V pa[3], d[3];
      for (int q = 0; q < 3; ++q) pa[q] = p[q] - c.a[q];
      V hr = zero, h = zero;
      if (c.type == kCapsule) {
        hr = (pa[0] * c.ab[0] + pa[1] * c.ab[1] + pa[2] * c.ab[2]) / c.abab;
        h = lane_min(lane_max(hr, zero), one);
      }
      for (int q = 0; q < 3; ++q) d[q] = c.type == kCapsule ? pa[q] - h * c.ab[q] : pa[q];
      unit_or_adjoint<V, T>(d, sbar, nbar, pbar);
      if (c.type == kCapsule) {
        const V hb = -(pbar[0] * c.ab[0] + pbar[1] * c.ab[1] + pbar[2] * c.ab[2]);
        const V hrb = select((hr >= T(0)) & (hr <= T(1)), hb / c.abab, zero);
        for (int q = 0; q < 3; ++q) pbar[q] = pbar[q] + hrb * c.ab[q];
      }
      return;
    }
    case kPlane:
      for (int q = 0; q < 3; ++q) pbar[q] = sbar * c.b[q];
      return;
    case kMesh: {
      V raw[3], coord[3], outside[3], g[3];
      const int64_t size[3] = {c.nx, c.ny, c.nz};
      for (int q = 0; q < 3; ++q) {
        raw[q] = c.bias[q] + p[q] * c.scale[q];
        coord[q] = lane_min(lane_max(raw[q], splat<V, T>(T(-1))), one);
        outside[q] = (raw[q] - coord[q]) / c.scale[q];
        g[q] = grid_coordinate<V, T>(coord[q], size[q]);
      }
      V s[4];
      trilinear4<V, T>(c, g[0], g[1], g[2], s);
      const V dist_out = norm3<V, T>(outside);
      const auto away = dist_out > T(0);
      const V safe_out = select(away, dist_out, one);
      V grad[3];
      for (int q = 0; q < 3; ++q) grad[q] = s[1 + q] + select(away, outside[q] / safe_out, zero);
      const V gn = norm3<V, T>(grad);
      const auto ok = gn > T(1e-12);
      const V gnc = lane_max(gn, splat<V, T>(T(1e-12)));
      // n = grad / max(|grad|, 1e-12) where |grad| > 1e-12 (else "up": no gradient)
      const V gncb = select(ok, -dot3(nbar, grad) / (gnc * gnc), zero);
      const V per = select(ok, gncb / select(ok, gn, one), zero);
      V gradb[3];
      for (int q = 0; q < 3; ++q) gradb[q] = select(ok, nbar[q] / gnc, zero) + per * grad[q];
      // grad = s[1:] + outside / |outside| (away); σ = s[0] + |outside|
      V outb[3];
      V distb = sbar - select(away, dot3(gradb, outside) / (safe_out * safe_out), zero);
      const V dper = select(away, distb / safe_out, zero);
      for (int q = 0; q < 3; ++q) outb[q] = select(away, gradb[q] / safe_out, zero) + dper * outside[q];
      // the trilinear sample's slope, lane by lane
      V coordb[3] = {zero, zero, zero};
      for (int l = 0; l < L::kWidth; ++l) {
        T dd[4][3];
        trilinear4_slope<T>(c, L::get(g[0], l), L::get(g[1], l), L::get(g[2], l), dd);
        const T sb[4] = {L::get(sbar, l), L::get(gradb[0], l), L::get(gradb[1], l), L::get(gradb[2], l)};
        for (int q = 0; q < 3; ++q) {
          const T acc = sb[0] * dd[0][q] + sb[1] * dd[1][q] + sb[2] * dd[2][q] + sb[3] * dd[3][q];
          L::set(coordb[q], l, acc * (T(0.5) * T(size[q] - 1)));
        }
      }
      for (int q = 0; q < 3; ++q) {
        coordb[q] = coordb[q] - outb[q] / c.scale[q];
        const V rawb = outb[q] / c.scale[q] + select((raw[q] >= T(-1)) & (raw[q] <= T(1)), coordb[q], zero);
        pbar[q] = rawb * c.scale[q];
      }
      return;
    }
    default: // hollow sphere: not differentiated here (the torch side never sends one)
      for (int q = 0; q < 3; ++q) pbar[q] = zero;
      return;
  }
}

// Adjoint of contact_response (response.contact_response): given ō = ∂L/∂v', the adjoints of
// v, v_c, n and μ.
template <class V, class T>
AMS_HD void contact_response_adjoint(const V v[3], const V vc[3], const V n[3], T mu, const V ob[3], V vb[3],
                                     V vcb[3], V nb[3], V& mub) {
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  V vrel[3], vt[3];
  for (int q = 0; q < 3; ++q) vrel[q] = v[q] - vc[q];
  const V vn = dot3(vrel, n);
  for (int q = 0; q < 3; ++q) vt[q] = vrel[q] - vn * n[q];
  const V len = norm3<V, T>(vt);
  const auto positive = len > T(0);
  const V dvn = lane_max(-vn, zero);
  const V lc = lane_max(len, splat<V, T>(T(1e-30)));
  const V kraw = T(1) - mu * dvn / lc;
  const V keep = select(positive, lane_max(kraw, zero), zero);
  const V vnp = lane_max(vn, zero);
  // out = v_c + max(vn, 0) n + keep v_t
  V vtb[3];
  const V sb = dot3(ob, n);
  const V kb = select(positive, dot3(ob, vt), zero);
  for (int q = 0; q < 3; ++q) {
    vcb[q] = ob[q];
    nb[q] = vnp * ob[q];
    vtb[q] = keep * ob[q];
  }
  const V krb = select(kraw >= T(0), kb, zero);
  mub = -krb * dvn / lc;
  const V dvnb = -krb * mu / lc;
  const V lb = select(len >= T(1e-30), krb * (mu * dvn) / (lc * lc), zero);
  V vnb = select(vn >= T(0), sb, zero) - select(-vn >= T(0), dvnb, zero);
  const V per = select(positive, lb / select(positive, len, one), zero);
  for (int q = 0; q < 3; ++q) vtb[q] = vtb[q] + per * vt[q];
  // v_t = v_rel − vn n;  vn = v_rel · n
  vnb = vnb - dot3(vtb, n);
  for (int q = 0; q < 3; ++q) {
    nb[q] = nb[q] - vn * vtb[q] + vnb * vrel[q];
    const V vrelb = vtb[q] + vnb * n[q];
    vb[q] = vrelb;
    vcb[q] = vcb[q] - vrelb;
  }
}

// Adjoint of l = Rᵀ (x − t) (to_local): given l̄, adds x̄ += R l̄, and to the pose R̄ += (x − t) l̄ᵀ,
// t̄ −= R l̄.
template <class V, class T>
AMS_HD void to_local_adjoint(const Prepared<T>& c, const V x[3], const V lb[3], V xb[3], V g[kPoseGrads]) {
  for (int i = 0; i < 3; ++i) {
    const V rl = c.R[3 * i] * lb[0] + c.R[3 * i + 1] * lb[1] + c.R[3 * i + 2] * lb[2];
    xb[i] = xb[i] + rl;
    g[9 + i] = g[9 + i] - rl;
    const V xi = x[i] - c.t[i];
    for (int j = 0; j < 3; ++j) g[3 * i + j] = g[3 * i + j] + xi * lb[j];
  }
}

// Adjoint of n = R n_local (rotate_normal): given n̄, n̄_local = Rᵀ n̄ and R̄ += n̄ n_localᵀ.
template <class V, class T>
AMS_HD void rotate_normal_adjoint(const Prepared<T>& c, const V nl[3], const V nb[3], V nlb[3], V g[kPoseGrads]) {
  for (int j = 0; j < 3; ++j) nlb[j] = nb[0] * c.R[j] + nb[1] * c.R[3 + j] + nb[2] * c.R[6 + j];
  for (int r = 0; r < 3; ++r)
    for (int j = 0; j < 3; ++j) g[3 * r + j] = g[3 * r + j] + nb[r] * nl[j];
}

// One push-out pass at xn: its local point, σ, local normal, depth and world normal.
template <class V, class T>
AMS_HD void pushout_terms(const Prepared<T>& c, const V xn[3], V l2[3], V& s2, V n2l[3], V& depth, V n2[3]) {
  to_local(c, xn, l2);
  distance_and_normal<V, T>(c, l2, s2, n2l);
  depth = lane_max(-s2, splat<V, T>(T(0)));
  rotate_normal(c, n2l, n2);
}

// Adjoint of `respond` (one collider on one particle) at its input (x, v): xb, vb hold the
// adjoints of its output and receive those of its input; the pose's and μ's adjoints are added
// to acc (kPoseGrads values), in the lanes where the particle is inside.
template <class V, class T, class M>
AMS_HD void respond_adjoint(const Prepared<T>& c, T dt, const M& free, const V x[3], const V v[3], V xb[3], V vb[3],
                            V acc[kPoseGrads]) {
  V local[3], nl[3], n[3], sigma;
  to_local(c, x, local);
  if (c.type == kMesh && mesh_surely_outside<V, T>(c, local)) return;
  distance_and_normal<V, T>(c, local, sigma, nl);
  const auto inside = (sigma < T(0)) & free;
  if (!any_lane(inside)) return;
  const V zero = splat<V, T>(T(0));
  rotate_normal(c, nl, n);
  V vc[3], r[3];
  for (int q = 0; q < 3; ++q) r[q] = x[q] - c.t[q];
  if (c.has_velocity) {
    vc[0] = c.lin[0] + (c.ang[1] * r[2] - c.ang[2] * r[1]);
    vc[1] = c.lin[1] + (c.ang[2] * r[0] - c.ang[0] * r[2]);
    vc[2] = c.lin[2] + (c.ang[0] * r[1] - c.ang[1] * r[0]);
  } else {
    vc[0] = vc[1] = vc[2] = zero;
  }
  V vn[3], xs[kMaxPushout + 1][3];
  contact_response<V, T>(v, vc, n, c.mu, vn);
  for (int q = 0; q < 3; ++q) xs[0][q] = x[q] + dt * (vn[q] - v[q]);
  for (int it = 0; it < c.iterations; ++it) {
    V l2[3], n2l[3], n2[3], s2, depth;
    pushout_terms<V, T>(c, xs[it], l2, s2, n2l, depth, n2);
    for (int q = 0; q < 3; ++q) xs[it + 1][q] = xs[it][q] + depth * n2[q];
  }
  V g[kPoseGrads];
  for (int k = 0; k < kPoseGrads; ++k) g[k] = zero;
  V ab[3] = {xb[0], xb[1], xb[2]}; // adjoint of the pushed position
  for (int it = c.iterations - 1; it >= 0; --it) {
    V l2[3], n2l[3], n2[3], s2, depth;
    pushout_terms<V, T>(c, xs[it], l2, s2, n2l, depth, n2);
    const V db = dot3(ab, n2);
    V n2b[3], n2lb[3], l2b[3];
    for (int q = 0; q < 3; ++q) n2b[q] = depth * ab[q];
    rotate_normal_adjoint<V, T>(c, n2l, n2b, n2lb, g);
    const V s2b = select(-s2 >= T(0), -db, zero);
    distance_and_normal_adjoint<V, T>(c, l2, s2b, n2lb, l2b);
    to_local_adjoint<V, T>(c, xs[it], l2b, ab, g);
  }
  // x_0 = x + Δt (v' − v)
  V xbn[3], vbn[3], vnb[3], vcb[3], nb[3], nlb[3], lb[3], mub;
  for (int q = 0; q < 3; ++q) {
    xbn[q] = ab[q];
    vnb[q] = vb[q] + dt * ab[q];
  }
  contact_response_adjoint<V, T>(v, vc, n, c.mu, vnb, vbn, vcb, nb, mub);
  for (int q = 0; q < 3; ++q) vbn[q] = vbn[q] - dt * ab[q];
  g[18] = mub;
  if (c.has_velocity) { // v_c = lin + ω × (x − t)
    const V ang[3] = {splat<V, T>(c.ang[0]), splat<V, T>(c.ang[1]), splat<V, T>(c.ang[2])};
    const V rb[3] = {vcb[1] * ang[2] - vcb[2] * ang[1], vcb[2] * ang[0] - vcb[0] * ang[2],
                     vcb[0] * ang[1] - vcb[1] * ang[0]};
    g[15] = g[15] + (r[1] * vcb[2] - r[2] * vcb[1]);
    g[16] = g[16] + (r[2] * vcb[0] - r[0] * vcb[2]);
    g[17] = g[17] + (r[0] * vcb[1] - r[1] * vcb[0]);
    for (int q = 0; q < 3; ++q) {
      g[12 + q] = g[12 + q] + vcb[q];
      xbn[q] = xbn[q] + rb[q];
      g[9 + q] = g[9 + q] - rb[q];
    }
  }
  rotate_normal_adjoint<V, T>(c, nl, nb, nlb, g);
  distance_and_normal_adjoint<V, T>(c, local, zero, nlb, lb);
  to_local_adjoint<V, T>(c, x, lb, xbn, g);
  for (int q = 0; q < 3; ++q) {
    xb[q] = select(inside, xbn[q], xb[q]);
    vb[q] = select(inside, vbn[q], vb[q]);
  }
  for (int k = 0; k < kPoseGrads; ++k) acc[k] = acc[k] + select(inside, g[k], zero);
}

// Adjoint of collide_strand at its input (xs, vs): xb, vb (3 N) hold the adjoints of its output
// and receive those of its input; acc: count × kPoseGrads pose adjoints.
template <class V, class T>
AMS_HD void collide_strand_adjoint(const Lanes<V, T>& xs, const Lanes<V, T>& vs, int64_t n, const V& pinned,
                                   const Prepared<T>* colliders, int count, T dt, const Lanes<V, T>& xb,
                                   const Lanes<V, T>& vb, V* acc) {
  for (int64_t i = 0; i < n; ++i) {
    V xc[kMaxColliders][3], vc[kMaxColliders][3], xi[3], vi[3], xbi[3], vbi[3];
    frame::load3(xs, i, xi);
    frame::load3(vs, i, vi);
    const auto free = T(i) >= pinned;
    for (int c = 0; c < count; ++c) {
      for (int q = 0; q < 3; ++q) {
        xc[c][q] = xi[q];
        vc[c][q] = vi[q];
      }
      if (c + 1 < count) respond<V, T>(colliders[c], dt, free, xi, vi);
    }
    frame::load3(xb, i, xbi);
    frame::load3(vb, i, vbi);
    for (int c = count - 1; c >= 0; --c)
      respond_adjoint<V, T>(colliders[c], dt, free, xc[c], vc[c], xbi, vbi, acc + c * kPoseGrads);
    frame::store3(xb, i, xbi);
    frame::store3(vb, i, vbi);
  }
}

// Workspace of one strand's stage adjoint (Lanes views).
template <class V, class T>
struct StageAdjoint {
  Lanes<V, T> hist;        // 6 N (1 + 2 rounds): x then v at the input of every sub-stage
  Lanes<V, T> xb, vb;      // 3 N: in: the adjoints of the stage's output; out: of its input
  Lanes<V, T> xb_new, lam; // 3 N: follow-the-leader's adjoint workspace
};

// The whole stage's adjoint for one strand. The caller fills snapshot 0 of w.hist with the
// stage's input (x, v) and w.xb, w.vb with the output adjoints. acc: count × kPoseGrads,
// headb: the head rotation's adjoint (9, row-major), both accumulated.
template <class V, class T>
AMS_HD void collision_stage_adjoint(const StageAdjoint<V, T>& w, const Lanes<V, T>& rest,
                                    const Lanes<V, T>& edge_length, int64_t n, const V& pinned,
                                    const Prepared<T>* colliders, int count, const CollideSettings& cfg,
                                    const T* head_rotation, V* acc, V headb[9]) {
  const int rounds = cfg.inextensibility ? cfg.rounds : 0;
  const int64_t per = 6 * n;
  auto snap = [&](int k, int part) { return Lanes<V, T>{w.hist.base + (per * k + 3 * n * part) * w.hist.stride,
                                                        w.hist.stride}; };
  for (int k = 1; k <= 2 * rounds; ++k) { // recompute: the input of sub-stage k is the output of k − 1
    for (int64_t e = 0; e < per; ++e) w.hist[per * k + e] = w.hist[per * (k - 1) + e];
    const Lanes<V, T> x = snap(k, 0), v = snap(k, 1);
    if (k == 1)
      collide_strand(x, v, n, pinned, colliders, count, T(cfg.dt));
    else if (k % 2 == 0)
      frame::follow_the_leader(x, v, rest, edge_length, pinned, head_rotation, T(cfg.ftl_damping), T(cfg.dt), n);
    else
      collide_strand(x, v, n, pinned, colliders, count, T(0));
  }
  frame::Strand<V, T> s{};
  s.n = n;
  s.rest = rest;
  s.rest_length[0] = edge_length;
  s.pinned = pinned;
  frame::Adjoint<V, T> adj{};
  adj.xb = w.xb;
  adj.vb = w.vb;
  adj.xb_new = w.xb_new;
  adj.lam = w.lam;
  for (int k = 2 * rounds; k >= 0; --k) {
    const Lanes<V, T> x = snap(k, 0), v = snap(k, 1);
    if (k == 0) {
      collide_strand_adjoint(x, v, n, pinned, colliders, count, T(cfg.dt), w.xb, w.vb, acc);
    } else if (k % 2 == 1) {
      s.x = x;
      s.v = v;
      V pb[12];
      for (int e = 0; e < 12; ++e) pb[e] = splat<V, T>(T(0));
      frame::ftl_adjoint(s, adj, head_rotation, T(cfg.ftl_damping), T(cfg.dt), pb);
      for (int e = 0; e < 9; ++e) headb[e] = headb[e] + pb[e];
    } else {
      collide_strand_adjoint(x, v, n, pinned, colliders, count, T(0), w.xb, w.vb, acc);
    }
  }
}

} // namespace collide
} // namespace ams_torch
