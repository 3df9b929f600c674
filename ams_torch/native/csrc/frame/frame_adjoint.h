// The adjoint (vector-Jacobian product) of one frame of strand dynamics (frame.h), per strand,
// written once for the host (frame_adjoint_cpu.cpp: W strands in SIMD lanes) and the device
// (frame_adjoint_cuda.cu: one thread per strand). The definition it differentiates is the torch
// frame (ams_torch/sim/dynamics.py::frame_dynamics with sim/assembly.py, sim/forces.py,
// sim/inextensibility.py); its gradients equal torch autograd's to rounding (tests/test_grad_native.py).
//
// Recompute, then reverse (no tape kept between the passes): the forward op stores nothing; the
// adjoint runs the frame's M substeps again (frame.h's own `advance`), keeping the state at every
// substep start (6 N (M + 1) values per strand), then walks back:
//
//   follow-the-leader:  the positions p_i are recomputed root to tip, then the chain rule runs tip
//                       to root (corrections c_i = p_i − x_i feed the velocity correction);
//   substep k (M − 1 … 0), from the state (x_k, v_k) and its result v' = v_{k+1}:
//     position update x_{k+1} = pinned ? target : x_k + Δt' v'       →  v̄' , target̄ , x̄_k
//     the solve A v' = b, A symmetric:  λ = A⁻¹ v̄'  with the same assembly and banded Cholesky
//                       as the forward (the adjoint solve reuses the SPD factorisation);
//                       b̄ = λ_f (λ with the pinned rows zeroed), Ā = −λ_f v'ᵀ (v' on pinned rows is
//                       their prescribed velocity, so this also covers the pinned columns moved to
//                       the right-hand side), v̄_pin = m λ_p − (A λ_f) on pinned rows;
//     each term's derivative contracted with (λ_f, v'): the diagonal (m + Δt' γ), m v, gravity, the
//                       external force, the edge / bend / torsion springs (and their geometric
//                       stiffness), the integrity spring (Hookean, or the non-Hookean law with its
//                       curve's transition, breaking point and soft ratio, its sag-free preload and
//                       tangent), the angular couple (force θ t̂ and its implicit tangent
//                       κ/|e| (I − êêᵀ) with the ghost-velocity term);
//     ghosts y = R_a ḡ + t_a and w = (R_b ḡ + t_b − y)/Δt', pin targets R_b X̄ + t_b  → ḡ̄ and the
//                       substep poses' (R, t) adjoints.
//
// Outputs per strand: x̄ and v̄ of the frame's input, ḡ̄ (ghost_rest), the external force's adjoint,
// the adjoints of every coefficient array (mass, drag, edge / bend / torsion stiffness, integrity,
// angular: the kernel takes coefficients per element as inputs, so how they come from Params does
// not matter here), of the non-Hookean curve's three numbers and the sag-free offset, and of the
// M + 1 substep poses (R row-major, then t: 12 values each; the torch side maps them to the frame's
// two head poses). The one-particle angular form is not differentiated here (the step keeps the
// torch definition for it). Ties of min / max in the non-Hookean curve split the gradient in halves
// as torch.minimum does; its clamp passes it at the kink (e = transition), as torch.clamp does.
//
// Conventions of the definition that the adjoint reproduces: safe_normalize's masked directions
// have zero derivative; the angular couple at alignment (|perp| = 0, cos > 0) has the derivative
// κ ∂perp (forces._aligned_derivative); a collapsed edge in follow-the-leader follows its fallback
// direction R (X̄_i − X̄_{i−1}) normalised, whose derivative reaches R.
#pragma once

#include <math.h>
#include <stdint.h>

#include "frame/frame.h"

namespace ams_torch {
namespace frame {

// Adjoint arrays of one strand (Lanes views of the kernel's workspace).
template <class V, class T>
struct Adjoint {
  Lanes<V, T> hist_x, hist_v;         // 3 N (M + 1): the state at every substep start, then before FTL
  Lanes<V, T> xb, vb;                 // 3 N: adjoints of x, v (in: of the frame's output; out: of its input)
  Lanes<V, T> xb_new, vb_new;         // 3 N: the adjoints of the current substep's start
  Lanes<V, T> lam;                    // 3 N: λ_f; also the positions of follow-the-leader
  Lanes<V, T> ya, yb, wb, vpb;        // 3 N: ghosts y at the substep start, adjoints of y, w, v_pin
  Lanes<V, T> gb;                     // 3 N: adjoint of ghost_rest (accumulated)
  Lanes<V, T> extb;                   // 3 N: adjoint of the external force (when there is one)
  Lanes<V, T> massb, dragb, integrityb; // N
  Lanes<V, T> stiffb[3];              // N − k
  Lanes<V, T> angularb;               // N − 1
  Lanes<V, T> poseb;                  // 12 (M + 1)
  Lanes<V, T> sagb;                   // 3 N: adjoint of sag_offset (non-Hookean law)
  Lanes<V, T> lawb;                   // 3: adjoints of the transition, breaking point and soft ratio
};

template <class V>
AMS_HD V dot3(const V a[3], const V b[3]) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

template <class V, class T>
AMS_HD void add3(const Lanes<V, T>& a, int64_t i, const V d[3]) {
  a[3 * i + 0] = a[3 * i + 0] + d[0];
  a[3 * i + 1] = a[3 * i + 1] + d[1];
  a[3 * i + 2] = a[3 * i + 2] + d[2];
}

template <class V, class T>
AMS_HD void sub3(const Lanes<V, T>& a, int64_t i, const V d[3]) {
  a[3 * i + 0] = a[3 * i + 0] - d[0];
  a[3 * i + 1] = a[3 * i + 1] - d[1];
  a[3 * i + 2] = a[3 * i + 2] - d[2];
}

// Adjoint of (unit, length) = safe_normalize(d) given ū and l̄: d̄ (zero where the direction is masked).
template <class V, class T>
AMS_HD void safe_normalize_adjoint(const V unit[3], const V& length, const V ubar[3], const V& lbar, V dbar[3]) {
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  const auto ok = length > T(0);
  const V inv = select(ok, one / select(ok, length, one), zero);
  const V uu = dot3(unit, ubar);
  for (int q = 0; q < 3; ++q) dbar[q] = select(ok, lbar * unit[q] + (ubar[q] - unit[q] * uu) * inv, zero);
}

// Rank-one update of a pose adjoint (R row-major 9, t 3): R̄ += a pᵀ, t̄ += a (with_t).
template <class V>
AMS_HD void pose_outer(V pb[12], const V a[3], const V p[3], bool with_t) {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) pb[3 * r + c] = pb[3 * r + c] + a[r] * p[c];
  if (with_t)
    for (int r = 0; r < 3; ++r) pb[9 + r] = pb[9 + r] + a[r];
}

// Rᵀ a for a row-major R.
template <class V, class T>
AMS_HD void rotate_t(const T* R, const V a[3], V out[3]) {
  for (int c = 0; c < 3; ++c) out[c] = R[c] * a[0] + R[3 + c] * a[1] + R[6 + c] * a[2];
}

// Adjoint of follow-the-leader (ftl.h) on the state before it (s.x, s.v): adj.xb, adj.vb hold the
// adjoints of its output and receive those of its input; the fallback directions' adjoint goes to
// the rotation R of `pb` (the last substep pose). adj.lam is used for the positions p_i.
template <class V, class T>
AMS_HD void ftl_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, const T* R, T damping, T dt, V pb[12]) {
  const int64_t n = s.n;
  const V zero = splat<V, T>(T(0));
  // positions p_i, root to tip (the forward's arithmetic)
  {
    V prev[3];
    load3(s.x, 0, prev);
    store3(adj.lam, 0, prev);
    for (int64_t i = 1; i < n; ++i) {
      V xi[3], d[3], unit[3], len, r1[3], r0[3], rd[3], rw[3], fb[3], fb_len;
      load3(s.x, i, xi);
      for (int c = 0; c < 3; ++c) d[c] = xi[c] - prev[c];
      safe_normalize(d, unit, len, T(1e-20));
      load3(s.rest, i, r1);
      load3(s.rest, i - 1, r0);
      for (int c = 0; c < 3; ++c) rd[c] = r1[c] - r0[c];
      rotate(R, rd, rw);
      safe_normalize(rw, fb, fb_len, T(1e-20));
      const V l = s.rest_length[0][i - 1];
      const auto pin_i = T(i) < s.pinned;
      for (int c = 0; c < 3; ++c) prev[c] = select(pin_i, xi[c], prev[c] + l * select(len > T(0), unit[c], fb[c]));
      store3(adj.lam, i, prev);
    }
  }
  // corrections c_i = p_i − x_i enter v_out_i (+1/dt) and v_out_{i−1} (−damping/dt), free rows only
  const T inv_dt = T(1) / dt;
  for (int64_t i = 1; i < n; ++i) {
    const auto free_i = T(i) >= s.pinned, free_p = T(i - 1) >= s.pinned;
    for (int c = 0; c < 3; ++c) {
      const V cb = select(free_i, adj.vb[3 * i + c] * inv_dt, zero) -
                   select(free_p, adj.vb[3 * (i - 1) + c] * (damping * inv_dt), zero);
      adj.xb[3 * i + c] = adj.xb[3 * i + c] + cb; // p̄_i (held in xb until the sweep reaches i)
      adj.xb_new[3 * i + c] = -cb;                // x̄_i
    }
  }
  for (int c = 0; c < 3; ++c) adj.xb_new[c] = zero;
  // tip to root: p̄_i → x̄_i (pinned) or p̄_{i−1} and the edge direction (free)
  for (int64_t i = n - 1; i >= 1; --i) {
    V xi[3], prev[3], d[3], unit[3], len, pbar[3];
    load3(s.x, i, xi);
    load3(adj.lam, i - 1, prev);
    load3(adj.xb, i, pbar);
    for (int c = 0; c < 3; ++c) d[c] = xi[c] - prev[c];
    safe_normalize(d, unit, len, T(1e-20));
    const V l = s.rest_length[0][i - 1];
    const auto pin_i = T(i) < s.pinned;
    const auto has_len = len > T(0);
    V dirb[3], dbar[3], fbb[3];
    for (int c = 0; c < 3; ++c) dirb[c] = select(pin_i, zero, l * pbar[c]);
    for (int c = 0; c < 3; ++c) fbb[c] = select(has_len, zero, dirb[c]);
    for (int c = 0; c < 3; ++c) dirb[c] = select(has_len, dirb[c], zero);
    safe_normalize_adjoint<V, T>(unit, len, dirb, zero, dbar);
    for (int c = 0; c < 3; ++c) {
      adj.xb_new[3 * i + c] = adj.xb_new[3 * i + c] + select(pin_i, pbar[c], dbar[c]);
      adj.xb[3 * (i - 1) + c] = adj.xb[3 * (i - 1) + c] + select(pin_i, zero, pbar[c] - dbar[c]);
    }
    // the fallback direction normalize(R (X̄_i − X̄_{i−1})): its adjoint reaches R
    V r1[3], r0[3], rd[3], rw[3], fb[3], fb_len, rwb[3];
    load3(s.rest, i, r1);
    load3(s.rest, i - 1, r0);
    for (int c = 0; c < 3; ++c) rd[c] = r1[c] - r0[c];
    rotate(R, rd, rw);
    safe_normalize(rw, fb, fb_len, T(1e-20));
    safe_normalize_adjoint<V, T>(fb, fb_len, fbb, zero, rwb);
    pose_outer(pb, rwb, rd, false);
  }
  for (int c = 0; c < 3; ++c) adj.xb_new[c] = adj.xb_new[c] + adj.xb[c]; // p_0 = x_0
  for (int64_t e = 0; e < 3 * n; ++e) adj.xb[e] = adj.xb_new[e];
}

// Springs between i and i + K: the force's and the matrix block's derivatives contracted with
// (λ_f, v'); x̄ into adj.xb_new, κ̄ into adj.stiffb, and −(A λ_f) on pinned rows into adj.vpb.
template <int K, class V, class T>
AMS_HD void springs_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, const Lanes<V, T>& vnew, T h, T h2,
                            bool geometric) {
  const int64_t pairs = s.n - K;
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  for (int64_t i = 0; i < pairs; ++i) {
    const int64_t j = i + K;
    V xi[3], xj[3], d[3], u[3], L, li[3], lj[3], vi[3], vj[3], dl[3], dv[3];
    load3(s.x, i, xi);
    load3(s.x, j, xj);
    for (int q = 0; q < 3; ++q) d[q] = xj[q] - xi[q];
    safe_normalize(d, u, L, T(1e-20));
    load3(adj.lam, i, li);
    load3(adj.lam, j, lj);
    load3(vnew, i, vi);
    load3(vnew, j, vj);
    for (int q = 0; q < 3; ++q) {
      dl[q] = li[q] - lj[q];
      dv[q] = vi[q] - vj[q];
    }
    const V kp = s.stiffness[K - 1][i], l0 = s.rest_length[K - 1][i];
    const V alpha = dot3(dl, u), beta = dot3(dv, u), dd = dot3(dl, dv);
    V g = zero, gp = zero; // geometric stiffness factor (1 − l/L)₊ and its derivative in L
    if (geometric) { // the forward's (1 − l'/L)₊, l' = l (1 + 1e-6)
      const V safe = select(L > T(0), L, one);
      const V slack = l0 * T(kGeometricSlack);
      const auto stretched = L > slack;
      g = select(stretched, one - slack / safe, zero);
      gp = select(stretched, slack / (safe * safe), zero);
    }
    const V keep = one - g;
    // σ = Δt' κ (L − l) α − Δt'² κ [(1 − g) α β + g Δλ·Δv']
    adj.stiffb[K - 1][i] = adj.stiffb[K - 1][i] + (h * ((L - l0) * alpha) - h2 * (keep * alpha * beta + g * dd));
    const V sL = h * kp * alpha - h2 * kp * (dd - alpha * beta) * gp;
    V su[3], db[3];
    for (int q = 0; q < 3; ++q) su[q] = h * kp * (L - l0) * dl[q] - h2 * kp * keep * (beta * dl[q] + alpha * dv[q]);
    safe_normalize_adjoint<V, T>(u, L, su, sL, db);
    add3(adj.xb_new, j, db);
    sub3(adj.xb_new, i, db);
    // v̄_pin: −(A λ_f) of the pair's block −Δt'² κ D, on both ends (read on pinned rows only)
    const V ul_j = dot3(u, lj), ul_i = dot3(u, li);
    for (int q = 0; q < 3; ++q) {
      adj.vpb[3 * i + q] = adj.vpb[3 * i + q] + h2 * kp * (keep * u[q] * ul_j + g * lj[q]);
      adj.vpb[3 * j + q] = adj.vpb[3 * j + q] + h2 * kp * (keep * u[q] * ul_i + g * li[q]);
    }
  }
}

// The angular couple of every segment (i, i + 1): force κ θ t̂ (on i + 1, −on i) and, when
// implicit, its tangent block Δt'² κ/|e| (I − êêᵀ) and the ghost-velocity term.
template <class V, class T>
AMS_HD void angular_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, const Lanes<V, T>& vnew,
                            const FrameSettings& cfg, T h, T h2) {
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  for (int64_t i = 0; i + 1 < s.n; ++i) {
    const int64_t j = i + 1;
    V x0[3], x1[3], y0[3], y1[3], e[3], g[3], eh[3], gh[3], elen, glen;
    load3(s.x, i, x0);
    load3(s.x, j, x1);
    load3(adj.ya, i, y0);
    load3(adj.ya, j, y1);
    for (int q = 0; q < 3; ++q) {
      e[q] = x1[q] - x0[q];
      g[q] = y1[q] - y0[q];
    }
    safe_normalize(e, eh, elen, T(1e-20));
    safe_normalize(g, gh, glen, T(1e-20));
    const V cs = dot3(eh, gh);
    V perp[3], th[3], sn;
    for (int q = 0; q < 3; ++q) perp[q] = gh[q] - eh[q] * cs;
    safe_normalize(perp, th, sn, T(1e-24));
    const V theta = lane_atan2<V, T>(sn, cs);
    const V kA = s.angular[i];
    V li[3], lj[3], mu[3], a[3];
    load3(adj.lam, i, li);
    load3(adj.lam, j, lj);
    for (int q = 0; q < 3; ++q) {
      mu[q] = lj[q] - li[q];
      a[q] = h * mu[q]; // the force's adjoint: Δt' (λ_j − λ_i)
    }
    const V at = dot3(a, th);
    V kbar = theta * at;
    // force κ θ t̂: θ̄ = κ a·t̂, t̂̄ = κ θ a
    const V thetab = kA * at;
    const V den = sn * sn + cs * cs;
    const V safe_den = select(den > T(0), den, one);
    const V sb = thetab * cs / safe_den, cb0 = -(thetab * sn) / safe_den;
    V thb[3], perpb[3];
    for (int q = 0; q < 3; ++q) thb[q] = kA * theta * a[q];
    safe_normalize_adjoint<V, T>(th, sn, thb, sb, perpb);
    const auto aligned = (sn == T(0)) & (cs > T(0));
    for (int q = 0; q < 3; ++q) perpb[q] = perpb[q] + select(aligned, kA * a[q], zero);
    // perp = ĝ − ê c, c = ê·ĝ
    V ehb[3], ghb[3];
    const V cb = cb0 - dot3(eh, perpb);
    for (int q = 0; q < 3; ++q) {
      ghb[q] = perpb[q] + cb * eh[q];
      ehb[q] = -cs * perpb[q] + cb * gh[q];
    }
    V lenb = zero;
    if (cfg.implicit_angular) {
      V w0[3], w1[3], v0[3], v1[3], z[3];
      load3(s.ghost_velocity, i, w0);
      load3(s.ghost_velocity, j, w1);
      load3(vnew, i, v0);
      load3(vnew, j, v1);
      for (int q = 0; q < 3; ++q) z[q] = (w1[q] - w0[q]) - (v1[q] - v0[q]);
      const auto positive = elen > T(0);
      const V inv_len = select(positive, one / select(positive, elen, one), zero);
      const V coef = kA * inv_len;
      const V mz = dot3(mu, z), me = dot3(mu, eh), ze = dot3(z, eh);
      const V Q = mz - me * ze; // μᵀ (I − êêᵀ) z
      kbar = kbar + h2 * inv_len * Q;
      lenb = select(positive, -(h2 * kA * Q) * inv_len * inv_len, zero);
      for (int q = 0; q < 3; ++q) ehb[q] = ehb[q] - h2 * coef * (ze * mu[q] + me * z[q]);
      // w̄ (b_j += Δt'² T Δw, b_i −= it) and v̄_pin (−(A λ_f) of the band block −Δt'² T)
      const V le_j = dot3(eh, lj), le_i = dot3(eh, li);
      for (int q = 0; q < 3; ++q) {
        const V tmu = h2 * coef * (mu[q] - eh[q] * me);
        adj.wb[3 * j + q] = adj.wb[3 * j + q] + tmu;
        adj.wb[3 * i + q] = adj.wb[3 * i + q] - tmu;
        adj.vpb[3 * i + q] = adj.vpb[3 * i + q] + h2 * coef * (lj[q] - eh[q] * le_j);
        adj.vpb[3 * j + q] = adj.vpb[3 * j + q] + h2 * coef * (li[q] - eh[q] * le_i);
      }
    }
    adj.angularb[i] = adj.angularb[i] + kbar;
    V eb[3], gb[3];
    safe_normalize_adjoint<V, T>(eh, elen, ehb, lenb, eb);
    safe_normalize_adjoint<V, T>(gh, glen, ghb, zero, gb);
    add3(adj.xb_new, j, eb);
    sub3(adj.xb_new, i, eb);
    add3(adj.yb, j, gb);
    sub3(adj.yb, i, gb);
  }
}

// The non-Hookean integrity spring of every particle (frame.h::add_integrity, forces.
// integrity_force_nonhookean): force κ off + κ L φ(e) û with the anchor y − off (off = R_a sag), its
// tangent Δt'² κ (φ' ûûᵀ + φ/e (I − ûûᵀ)) and ghost-velocity term, contracted with (λ_f, v');
// the curve's adjoints (transition, breaking, soft ratio) into adj.lawb, R_a's into pa_b.
template <class V, class T>
AMS_HD void integrity_nonhookean_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, const Material<T>& mat,
                                         const Lanes<V, T>& vnew, const T* pose_a, T h, T h2, V pa_b[12]) {
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1)), half = splat<V, T>(T(0.5));
  const T tr = mat.transition, span = mat.breaking - mat.transition, soft = T(1) - mat.soft_ratio;
  V tb = zero, bb = zero, rb = zero;
  for (int64_t i = 0; i < s.n; ++i) {
    V xi[3], y[3], w[3], vp[3], l[3], sag[3], off[3], d[3], u[3], dist, z[3];
    load3(s.x, i, xi);
    load3(adj.ya, i, y);
    load3(s.ghost_velocity, i, w);
    load3(vnew, i, vp);
    load3(adj.lam, i, l);
    load3(s.sag_offset, i, sag);
    rotate(pose_a, sag, off);
    for (int q = 0; q < 3; ++q) {
      d[q] = (y[q] - off[q]) - xi[q];
      z[q] = w[q] - vp[q];
    }
    safe_normalize(d, u, dist, T(1e-20));
    const V L = s.segment[i], kI = s.integrity[i];
    const V e = dist / L;
    // the curve (forces.integrity_elongation_law)
    const V em = e - tr;
    const V over = lane_max(em, zero);
    const V over_c = lane_min(over, splat<V, T>(span));
    const V below = lane_min(e, splat<V, T>(tr));
    const V phi = below + over_c - soft * over_c * over_c / (T(2) * span);
    const V slope = T(1) - soft * over_c / span;
    const auto stretched = e > T(0);
    const V safe_e = select(stretched, e, one);
    const V secant = select(stretched, phi / safe_e, one);
    // σ = Δt' λ·(κ off + κ L φ û) + Δt'² κ [secant λ·z + (slope − secant)(λ·û)(z·û)]
    const V P = dot3(l, u), Zu = dot3(z, u), LZ = dot3(l, z);
    adj.integrityb[i] = adj.integrityb[i] + (h * dot3(l, off) + h * L * phi * P +
                                             h2 * (secant * LZ + (slope - secant) * P * Zu));
    V phib = h * kI * L * P;
    const V slopeb = h2 * kI * P * Zu, secb = h2 * kI * (LZ - P * Zu);
    phib = phib + select(stretched, secb / safe_e, zero);
    V eb = select(stretched, -(secb * phi) / (safe_e * safe_e), zero);
    const V overcb = phib * slope - slopeb * soft / span;
    V spanb = phib * soft * over_c * over_c / (T(2) * span * span) + slopeb * soft * over_c / (span * span);
    rb = rb + phib * over_c * over_c / (T(2) * span) + slopeb * over_c / span;
    // over_c = min(over, span), below = min(e, t): ties split in halves (torch.minimum)
    const auto o_lt = over < span, o_eq = over == span;
    const V overb = select(o_lt, overcb, select(o_eq, half * overcb, zero));
    spanb = spanb + select(o_lt, zero, select(o_eq, half * overcb, overcb));
    const V emb = select(em >= T(0), overb, zero); // over = clamp(e − t, min=0)
    const auto b_lt = e < tr, b_eq = e == tr;
    eb = eb + emb + select(b_lt, phib, select(b_eq, half * phib, zero));
    tb = tb - emb + select(b_lt, zero, select(b_eq, half * phib, phib)) - spanb;
    bb = bb + spanb;
    // e = dist / L, û: the direction of d = (y − off) − x
    V ub[3], db[3];
    for (int q = 0; q < 3; ++q) ub[q] = h * kI * L * phi * l[q] + h2 * kI * (slope - secant) * (Zu * l[q] + P * z[q]);
    safe_normalize_adjoint<V, T>(u, dist, ub, eb / L, db);
    const auto at_anchor = dist == T(0); // forces._aligned_derivative: κ φ'(0) ∂d there
    V offb[3], sb[3];
    for (int q = 0; q < 3; ++q) {
      db[q] = db[q] + select(at_anchor, h * kI * slope * l[q], zero);
      adj.wb[3 * i + q] = adj.wb[3 * i + q] + h2 * kI * (secant * l[q] + (slope - secant) * P * u[q]);
      adj.xb_new[3 * i + q] = adj.xb_new[3 * i + q] - db[q];
      adj.yb[3 * i + q] = adj.yb[3 * i + q] + db[q];
      offb[q] = h * kI * l[q] - db[q];
    }
    rotate_t(pose_a, offb, sb);
    add3(adj.sagb, i, sb);
    pose_outer(pa_b, offb, sag, false);
  }
  adj.lawb[0] = adj.lawb[0] + tb;
  adj.lawb[1] = adj.lawb[1] + bb;
  adj.lawb[2] = adj.lawb[2] + rb;
}

// The adjoint of substep k (frame.h::advance from pose_a to pose_b): reads adj.xb, adj.vb (the
// adjoints of x_{k+1}, v_{k+1}) and the stored states; leaves the adjoints of x_k, v_k there.
template <class V, class T>
AMS_HD void substep_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, const Material<T>& mat,
                            const FrameSettings& cfg, const T* pose_a, const T* pose_b, int k) {
  const int64_t n = s.n;
  const double hd = cfg.dt / cfg.substeps;
  const T h = T(hd), h2 = T(hd * hd);
  const V zero = splat<V, T>(T(0));
  const Lanes<V, T> vnew{adj.hist_v.base + int64_t(3) * n * (k + 1) * adj.hist_v.stride, adj.hist_v.stride};
  for (int64_t e = 0; e < 3 * n; ++e) {
    s.x[e] = adj.hist_x[3 * n * k + e];
    s.v[e] = adj.hist_v[3 * n * k + e];
  }
  V pa_b[12], pb_b[12];
  for (int e = 0; e < 12; ++e) pa_b[e] = pb_b[e] = zero;
  // the system at (x_k, v_k), factored with λ = A⁻¹ v̄' as its right-hand side
  assemble(s, mat, cfg, pose_a, pose_b);
  for (int64_t i = 0; i < n; ++i) {
    const auto pin_i = T(i) < s.pinned;
    V r[3], tb[3];
    for (int q = 0; q < 3; ++q) {
      const V xb = adj.xb[3 * i + q];
      s.b[3 * i + q] = adj.vb[3 * i + q] + select(pin_i, zero, h * xb); // v̄'
      adj.xb_new[3 * i + q] = select(pin_i, zero, xb);
      tb[q] = select(pin_i, xb, zero); // target̄ from x_{k+1} = target on pinned rows
      adj.vb_new[3 * i + q] = zero;
      adj.yb[3 * i + q] = zero;
      adj.wb[3 * i + q] = zero;
      adj.vpb[3 * i + q] = zero;
    }
    if (i < s.pinned_max) {
      load3(s.rest, i, r);
      pose_outer(pb_b, tb, r, true);
    }
  }
  banded::solve_strand<V, T>(s.a, s.b, n);
  for (int64_t i = 0; i < n; ++i) { // λ_f, and m λ_p into v̄_pin
    const auto pin_i = T(i) < s.pinned;
    V g[3], ya[3];
    load3(s.ghost_rest, i, g);
    rigid_map(pose_a, pose_a + 9, g, ya);
    store3(adj.ya, i, ya);
    const V m = s.mass[i];
    for (int q = 0; q < 3; ++q) {
      const V l = s.b[3 * i + q];
      adj.lam[3 * i + q] = select(pin_i, zero, l);
      adj.vpb[3 * i + q] = select(pin_i, m * l, zero);
    }
  }
  // per particle: diagonal, m v, gravity, external force, Hookean integrity
  for (int64_t i = 0; i < n; ++i) {
    V l[3], vp[3], v0[3];
    load3(adj.lam, i, l);
    load3(vnew, i, vp);
    load3(s.v, i, v0);
    const V m = s.mass[i];
    V grav = zero;
    for (int q = 0; q < 3; ++q) grav = grav + l[q] * mat.gravity[q];
    adj.massb[i] = adj.massb[i] + ((dot3(l, v0) - dot3(l, vp)) + h * grav);
    adj.dragb[i] = adj.dragb[i] - h * dot3(l, vp);
    for (int q = 0; q < 3; ++q) adj.vb_new[3 * i + q] = m * l[q];
    if (s.has_ext)
      for (int q = 0; q < 3; ++q) adj.extb[3 * i + q] = adj.extb[3 * i + q] + h * l[q];
    if (cfg.integrity_model == kIntegrityHookean) {
      V xi[3], y[3], w[3];
      load3(s.x, i, xi);
      load3(adj.ya, i, y);
      load3(s.ghost_velocity, i, w);
      const V kI = s.integrity[i];
      V yx[3], wv[3];
      for (int q = 0; q < 3; ++q) {
        yx[q] = y[q] - xi[q];
        wv[q] = w[q] - vp[q];
      }
      adj.integrityb[i] = adj.integrityb[i] + (h * dot3(l, yx) + h2 * dot3(l, wv));
      for (int q = 0; q < 3; ++q) {
        adj.xb_new[3 * i + q] = adj.xb_new[3 * i + q] - h * kI * l[q];
        adj.yb[3 * i + q] = adj.yb[3 * i + q] + h * kI * l[q];
        adj.wb[3 * i + q] = adj.wb[3 * i + q] + h2 * kI * l[q];
      }
    }
  }
  if (cfg.integrity_model == kIntegrityNonHookean) integrity_nonhookean_adjoint(s, adj, mat, vnew, pose_a, h, h2, pa_b);
  springs_adjoint<1>(s, adj, vnew, h, h2, cfg.geometric_stiffness);
  springs_adjoint<2>(s, adj, vnew, h, h2, cfg.geometric_stiffness);
  springs_adjoint<3>(s, adj, vnew, h, h2, cfg.geometric_stiffness);
  if (cfg.angular) angular_adjoint(s, adj, vnew, cfg, h, h2);
  // pinned rows: v_pin = (target − x)/Δt'
  const int64_t pinned_rows = s.pinned_max < n ? s.pinned_max : n;
  for (int64_t i = 0; i < pinned_rows; ++i) {
    const auto pin_i = T(i) < s.pinned;
    V tb[3], r[3];
    for (int q = 0; q < 3; ++q) {
      const V vpb = select(pin_i, adj.vpb[3 * i + q] / h, zero);
      adj.xb_new[3 * i + q] = adj.xb_new[3 * i + q] - vpb;
      tb[q] = vpb;
    }
    load3(s.rest, i, r);
    pose_outer(pb_b, tb, r, true);
  }
  // ghosts y = R_a ḡ + t_a, w = (R_b ḡ + t_b − y)/Δt'
  const T inv_h = T(1) / h;
  for (int64_t i = 0; i < n; ++i) {
    V g[3], ybar[3], wbar[3], ga[3], gbv[3];
    load3(s.ghost_rest, i, g);
    for (int q = 0; q < 3; ++q) {
      wbar[q] = adj.wb[3 * i + q] * inv_h;
      ybar[q] = adj.yb[3 * i + q] - wbar[q];
    }
    rotate_t(pose_a, ybar, ga);
    rotate_t(pose_b, wbar, gbv);
    for (int q = 0; q < 3; ++q) adj.gb[3 * i + q] = adj.gb[3 * i + q] + (ga[q] + gbv[q]);
    pose_outer(pa_b, ybar, g, true);
    pose_outer(pb_b, wbar, g, true);
  }
  for (int e = 0; e < 12; ++e) {
    adj.poseb[12 * k + e] = adj.poseb[12 * k + e] + pa_b[e];
    adj.poseb[12 * (k + 1) + e] = adj.poseb[12 * (k + 1) + e] + pb_b[e];
  }
  for (int64_t e = 0; e < 3 * n; ++e) {
    adj.xb[e] = adj.xb_new[e];
    adj.vb[e] = adj.vb_new[e];
  }
}

// Zero the accumulated adjoints (ghost_rest, external force, coefficients, poses).
template <class V, class T>
AMS_HD void zero_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, int substeps) {
  const int64_t n = s.n;
  const V zero = splat<V, T>(T(0));
  for (int64_t e = 0; e < 3 * n; ++e) {
    adj.gb[e] = zero;
    adj.sagb[e] = zero;
    if (s.has_ext) adj.extb[e] = zero;
  }
  for (int e = 0; e < 3; ++e) adj.lawb[e] = zero;
  for (int64_t i = 0; i < n; ++i) adj.massb[i] = adj.dragb[i] = adj.integrityb[i] = zero;
  for (int k = 0; k < 3; ++k)
    for (int64_t i = 0; i + 1 + k < n; ++i) adj.stiffb[k][i] = zero;
  for (int64_t i = 0; i + 1 < n; ++i) adj.angularb[i] = zero;
  for (int64_t e = 0; e < 12 * (substeps + 1); ++e) adj.poseb[e] = zero;
}

// The whole frame's adjoint for one strand: s.x, s.v hold the frame's input state, adj.xb, adj.vb
// the adjoints of its output (x, v); on return adj.xb, adj.vb hold the adjoints of the input and
// the accumulated arrays of Adjoint the others. `poses`: the M + 1 substep poses (kPoseElems each).
template <class V, class T>
AMS_HD void strand_frame_adjoint(const Strand<V, T>& s, const Adjoint<V, T>& adj, const Material<T>& mat,
                                 const FrameSettings& cfg, const T* poses) {
  const int64_t n = s.n;
  const int M = cfg.substeps;
  zero_adjoint(s, adj, M);
  for (int k = 0; k < M; ++k) {
    for (int64_t e = 0; e < 3 * n; ++e) {
      adj.hist_x[3 * n * k + e] = s.x[e];
      adj.hist_v[3 * n * k + e] = s.v[e];
    }
    advance(s, mat, cfg, poses + kPoseElems * k, poses + kPoseElems * (k + 1));
  }
  for (int64_t e = 0; e < 3 * n; ++e) {
    adj.hist_x[3 * n * M + e] = s.x[e];
    adj.hist_v[3 * n * M + e] = s.v[e];
  }
  if (cfg.inextensibility) {
    V pb[12];
    for (int e = 0; e < 12; ++e) pb[e] = splat<V, T>(T(0));
    ftl_adjoint(s, adj, poses + kPoseElems * M, T(cfg.ftl_damping), T(cfg.dt), pb);
    for (int e = 0; e < 9; ++e) adj.poseb[12 * M + e] = adj.poseb[12 * M + e] + pb[e];
  }
  for (int k = M - 1; k >= 0; --k)
    substep_adjoint(s, adj, mat, cfg, poses + kPoseElems * k, poses + kPoseElems * (k + 1), k);
}

} // namespace frame
} // namespace ams_torch
