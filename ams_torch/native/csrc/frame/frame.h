// One frame of strand dynamics, fused per strand (SPEC §4, §15), written once for the host (CPU
// kernel, frame_cpu.cpp: W strands in SIMD lanes) and the device (CUDA kernel, frame_cuda.cu:
// one thread per strand). The torch definition is ams_torch/sim/dynamics.py::frame_dynamics with
// the terms of sim/assembly.py and sim/forces.py; this is the same arithmetic, in the same order
// wherever that is practical (float64 results agree to rounding):
//
//   poses:  the M + 1 head poses of the substep ends (Pose.interpolate: relative rotation vector,
//           slerp, cubic Hermite or linear translation; pose 0 and pose M are the frame's own),
//           computed once per scene by `substep_pose` (scalar T);
//   for each substep k (Δt' = dt / M), from pose k (a) to pose k + 1 (b):
//     ghosts y = R_a ḡ + t_a, their velocity w = ((R_b ḡ + t_b) − y) / Δt';
//     the system of assembly.assemble_system (`assemble`): diagonal (m + Δt' γ) I, gravity m g and
//     the external force; edge / bend / torsion springs κ D (with the geometric stiffness
//     κ (1 − l/|d|)₊ (I − D) when on); the integrity spring (Hookean, or the non-Hookean law with
//     its tangent); the angular spring (couple or one-particle form, implicit or explicit); the
//     ghost-velocity terms; rhs = m v + Δt'² (ghost terms) + Δt' f; then the pinned rows
//     (rhs −= A v_pin on pinned columns, pinned rows m I v = m v_pin);
//     the banded Cholesky solve (banded_cholesky.h::solve_strand) for the new velocities;
//     x = pin targets (R_b X̄ + t_b) on pinned particles, x + Δt' v elsewhere;
//   then follow-the-leader (ftl.h) with the end pose's rotation, when inextensibility is on.
//   With substep contact (Params(contact="substep"); dynamics.frame_dynamics' `contact`, the torch
//   definition sim/contact.py::substep_contact), after each substep's position update every
//   collider's response with Δt' at its world pose for that substep (collide.h::collide_strand).
//
// Data layout: every array of one strand is a Lanes<V, T> view (element e at base + e·stride):
// rows of 3 for positions, one value per particle / pair for coefficients, the matrix in the row
// layout of banded_cholesky.h (row i, element 9k + 3r + c = A[i, i−k](r, c)). Symmetric 3×3
// blocks are built as their 6 lower entries (00, 10, 11, 20, 21, 22) and mirrored exactly.
#pragma once

#include <math.h>
#include <stdint.h>

#include "banded/banded_cholesky.h"
#include "collide/collide.h"
#include "frame/ftl.h"
#include "frame/lanes.h"

namespace ams_torch {
namespace frame {

constexpr int kPoseElems = 12; // row-major R (9), then t (3)
// l' / l of the geometric stiffness (1 − l'/L)₊: edges follow-the-leader left at their rest length
// (up to rounding) get no term (sim/forces.py GEOMETRIC_SLACK)
constexpr double kGeometricSlack = 1.000001;
constexpr int kRow = banded::kRowElems;

enum IntegrityModel { kIntegrityNone = 0, kIntegrityHookean = 1, kIntegrityNonHookean = 2 };

// The Config of the step that the kernels read: the one list of the C++ side, in the order of its
// Python twin (FrameSettings of ams_torch/sim/op_support.py, whose field names these are; the tests
// compare the two). X(member type, name, op parameter type, schema type). The struct, the ops'
// schemas, the bindings' parameters and arguments and the struct's initialiser are made from it:
// a flag of the kernels is one line here and its use.
//   dt: frame length, s; substeps: M; ftl_damping: Müller's velocity-correction factor;
//   integrity_model: IntegrityModel; the rest: the Config flags.
#define AMS_FRAME_SETTINGS(X)                   \
  X(double, dt, double, "float")                \
  X(int, substeps, int64_t, "int")              \
  X(double, ftl_damping, double, "float")       \
  X(int, integrity_model, int64_t, "int")       \
  X(bool, angular, bool, "bool")                \
  X(bool, angular_reaction, bool, "bool")       \
  X(bool, implicit_angular, bool, "bool")       \
  X(bool, geometric_stiffness, bool, "bool")    \
  X(bool, inextensibility, bool, "bool")

// Pieces of the bindings, each with its leading comma: ", float dt, int substeps, ..." (schema),
// ", double dt, int64_t substeps, ..." (parameters), ", dt, substeps, ..." (arguments), and
// "double(dt), int(substeps), ..., " (the struct's initialiser, before hermite).
#define AMS_FRAME_SETTING_SCHEMA_(member_t, name, param_t, schema_t) ", " schema_t " " #name
#define AMS_FRAME_SETTING_PARAM_(member_t, name, param_t, schema_t) , param_t name
#define AMS_FRAME_SETTING_ARG_(member_t, name, param_t, schema_t) , name
#define AMS_FRAME_SETTING_INIT_(member_t, name, param_t, schema_t) member_t(name),
#define AMS_FRAME_SETTINGS_SCHEMA AMS_FRAME_SETTINGS(AMS_FRAME_SETTING_SCHEMA_)
#define AMS_FRAME_SETTINGS_PARAMS AMS_FRAME_SETTINGS(AMS_FRAME_SETTING_PARAM_)
#define AMS_FRAME_SETTINGS_ARGS AMS_FRAME_SETTINGS(AMS_FRAME_SETTING_ARG_)
#define AMS_FRAME_SETTINGS_INIT AMS_FRAME_SETTINGS(AMS_FRAME_SETTING_INIT_)

struct FrameSettings {
#define AMS_FRAME_SETTING_MEMBER_(member_t, name, param_t, schema_t) member_t name;
  AMS_FRAME_SETTINGS(AMS_FRAME_SETTING_MEMBER_)
#undef AMS_FRAME_SETTING_MEMBER_
  bool hermite; // the frame's poses carry velocities (a per-frame fact, not Config's)
};

// Raw pointers of one call (all contiguous; the torch bindings check shapes and dtypes).
template <class T>
struct FrameArgs {
  int64_t scenes, strands, particles; // B (leading scene dims flattened), S, N
  // per scene (B, S, N, 3)
  const T* x;
  const T* v;
  const T* ghost_rest;
  const T* sag_offset;
  const T* external_force; // nullptr: none
  // per strand
  const T* rest_positions;  // (S, N, 3)
  const T* mass;            // (S, N) kg
  const T* drag;            // (S, N) kg/s
  const T* stiffness[3];    // (S, N − k) N/m: edge, bend, torsion
  const T* rest_length[3];  // (S, N − k) m
  const T* integrity;       // (S, N) N/m
  const T* angular;         // (S, N − 1) N/rad
  const T* segment_length;  // (S, N) m
  const int64_t* num_pinned; // (S,)
  // shared scalars
  const T* gravity;    // (3,) m/s²
  const T* transition; // ()
  const T* breaking;   // ()
  const T* soft_ratio; // ()
  // the frame's start (0) and end (1) head poses: (P_j, 3, 3), (P_j, 3), (P_j, 3), P_j ∈ {1, B}
  const T* rotation[2];
  const T* translation[2];
  const T* velocity[2]; // linear velocity, read only with hermite
  int64_t pose_scenes[2];
};

// Shared scalars of the material, read once.
template <class T>
struct Material {
  T gravity[3];
  T transition, breaking, soft_ratio;
};

// ---------------------------------------------------------------------------------------
// head poses of the substeps (geometry/pose.py), scalar T
// ---------------------------------------------------------------------------------------

template <class T>
struct ScalarMath;
template <>
struct ScalarMath<float> {
  static AMS_HD float sin(float x) { return ::sinf(x); }
  static AMS_HD float cos(float x) { return ::cosf(x); }
  static AMS_HD float atan2(float y, float x) { return ::atan2f(y, x); }
  static AMS_HD float sqrt(float x) { return ::sqrtf(x); }
  static constexpr float kThetaFloor = 1e-30f; // axis_angle_to_matrix's clamp under the sqrt
};
template <>
struct ScalarMath<double> {
  static AMS_HD double sin(double x) { return ::sin(x); }
  static AMS_HD double cos(double x) { return ::cos(x); }
  static AMS_HD double atan2(double y, double x) { return ::atan2(y, x); }
  static AMS_HD double sqrt(double x) { return ::sqrt(x); }
  static constexpr double kThetaFloor = 1e-300;
};

template <class T>
AMS_HD T smax(T a, T b) {
  return b > a ? b : a;
}

// c = a @ b for row-major 3×3 (torch.matmul order: ((a_r0 b_0c + a_r1 b_1c) + a_r2 b_2c)).
template <class T>
AMS_HD void matmul3(const T* a, const T* b, T* c) {
  for (int r = 0; r < 3; ++r)
    for (int q = 0; q < 3; ++q) c[3 * r + q] = a[3 * r + 0] * b[0 + q] + a[3 * r + 1] * b[3 + q] + a[3 * r + 2] * b[6 + q];
}

// Pose.relative_rotvec: matrix_to_axis_angle(R1 R0ᵀ), with its small-angle branch.
template <class T>
AMS_HD void relative_rotvec(const T* R0, const T* R1, T rv[3]) {
  using S = ScalarMath<T>;
  T m[9];
  for (int r = 0; r < 3; ++r)
    for (int q = 0; q < 3; ++q) m[3 * r + q] = R1[3 * r + 0] * R0[3 * q + 0] + R1[3 * r + 1] * R0[3 * q + 1] + R1[3 * r + 2] * R0[3 * q + 2];
  const T w[3] = {m[7] - m[5], m[2] - m[6], m[3] - m[1]};
  T cs = ((m[0] + m[4] + m[8]) - T(1)) / T(2);
  cs = cs < T(-1) ? T(-1) : (cs > T(1) ? T(1) : cs);
  const T sn = T(0.5) * S::sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
  const T theta = S::atan2(sn, cs);
  const T scale = sn > T(1e-7) ? theta / (T(2) * smax(sn, T(1e-30))) : T(0.5) + theta * theta / T(12);
  for (int c = 0; c < 3; ++c) rv[c] = w[c] * scale;
}

// axis_angle_to_matrix(q) (Rodrigues, with its Taylor branch near 0).
template <class T>
AMS_HD void axis_angle_to_matrix(const T q[3], T R[9]) {
  using S = ScalarMath<T>;
  const T theta2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
  const T theta = S::sqrt(smax(theta2, S::kThetaFloor));
  const bool small = theta2 < T(1e-12);
  const T a = small ? T(1) - theta2 / T(6) : S::sin(theta) / theta;
  const T b = small ? T(0.5) - theta2 / T(24) : (T(1) - S::cos(theta)) / smax(theta2, T(1e-30));
  const T k[9] = {T(0), -q[2], q[1], q[2], T(0), -q[0], -q[1], q[0], T(0)};
  T kk[9];
  matmul3(k, k, kk);
  for (int e = 0; e < 9; ++e) R[e] = ((e % 4 == 0 ? T(1) : T(0)) + a * k[e]) + b * kk[e];
}

// Head pose (R, t) at the end of substep k − 1, i.e. at fraction k / M of the frame, for scene
// `scene` (dynamics.substep_poses and Pose.interpolate): k = 0 and k = M are the frame's own
// poses; in between, R = axis_angle_to_matrix(rv · s) R0 with rv the relative rotation vector,
// and t the cubic Hermite of the two translations and velocities (when `hermite`) or linear.
template <class T>
AMS_HD void substep_pose(const FrameArgs<T>& a, int64_t scene, int k, int substeps, bool hermite, double dt, T* out) {
  const int64_t p0 = a.pose_scenes[0] == 1 ? 0 : scene;
  const int64_t p1 = a.pose_scenes[1] == 1 ? 0 : scene;
  const T* R0 = a.rotation[0] + 9 * p0;
  const T* t0 = a.translation[0] + 3 * p0;
  const T* R1 = a.rotation[1] + 9 * p1;
  const T* t1 = a.translation[1] + 3 * p1;
  if (k <= 0 || k >= substeps) {
    const T* R = k <= 0 ? R0 : R1;
    const T* t = k <= 0 ? t0 : t1;
    for (int e = 0; e < 9; ++e) out[e] = R[e];
    for (int c = 0; c < 3; ++c) out[9 + c] = t[c];
    return;
  }
  const double s = double(k) / double(substeps);
  T rv[3], q[3], rs[9];
  relative_rotvec(R0, R1, rv);
  for (int c = 0; c < 3; ++c) q[c] = rv[c] * T(s);
  axis_angle_to_matrix(q, rs);
  matmul3(rs, R0, out);
  if (hermite) {
    const T* u0 = a.velocity[0] + 3 * p0;
    const T* u1 = a.velocity[1] + 3 * p1;
    const double s2 = pow(s, 2.0), s3 = pow(s, 3.0);
    const T h00 = T(2 * s3 - 3 * s2 + 1), h10 = T(s3 - 2 * s2 + s), h01 = T(-2 * s3 + 3 * s2), h11 = T(s3 - s2);
    for (int c = 0; c < 3; ++c) {
      const T v0 = u0[c] * T(dt), v1 = u1[c] * T(dt);
      out[9 + c] = h00 * t0[c] + h10 * v0 + h01 * t1[c] + h11 * v1;
    }
  } else {
    for (int c = 0; c < 3; ++c) out[9 + c] = T(1 - s) * t0[c] + T(s) * t1[c];
  }
}

// ---------------------------------------------------------------------------------------
// one strand (or W strands in lanes)
// ---------------------------------------------------------------------------------------

template <class V, class T>
struct Strand {
  int64_t n; // particles
  // per strand: model data
  Lanes<V, T> rest;           // 3N, head frame
  Lanes<V, T> mass, drag;     // N
  Lanes<V, T> stiffness[3];   // N − k
  Lanes<V, T> rest_length[3]; // N − k
  Lanes<V, T> integrity;      // N
  Lanes<V, T> angular;        // N − 1
  Lanes<V, T> segment;        // N
  V pinned;                   // pinned prefix length, as a value of T per lane
  int pinned_max;             // its maximum over the lanes
  // per scene
  Lanes<V, T> x, v, ghost_rest, sag_offset; // 3N each; x, v updated in place
  Lanes<V, T> ext;                          // 3N, read when has_ext
  bool has_ext;
  // workspace
  Lanes<V, T> a;     // N rows of 36: the matrix, factored in place by the solve
  Lanes<V, T> b;     // 3N: right-hand side, then the new velocities
  Lanes<V, T> force; // 3N: forces; then the pinned particles' prescribed velocities
  Lanes<V, T> ghost; // 3N: ghosts at the substep start; then the pinned particles' targets
  Lanes<V, T> ghost_velocity; // 3N
};

// Add a symmetric block (6 lower entries) to the diagonal block of row i (lower triangle only;
// `mirror_blocks` completes the upper one).
template <class V, class T>
AMS_HD void add_diag(const Lanes<V, T>& a, int64_t i, const V s[6]) {
  const int64_t r = i * kRow;
  a[r + 0] = a[r + 0] + s[0];
  a[r + 3] = a[r + 3] + s[1];
  a[r + 4] = a[r + 4] + s[2];
  a[r + 6] = a[r + 6] + s[3];
  a[r + 7] = a[r + 7] + s[4];
  a[r + 8] = a[r + 8] + s[5];
}

// Write the symmetric block s (6 lower entries) as A[i, i − k] (all 9 entries).
template <class V, class T>
AMS_HD void set_block(const Lanes<V, T>& a, int64_t i, int k, const V s[6]) {
  const int64_t r = i * kRow + 9 * k;
  a[r + 0] = s[0];
  a[r + 1] = s[1];
  a[r + 2] = s[3];
  a[r + 3] = s[1];
  a[r + 4] = s[2];
  a[r + 5] = s[4];
  a[r + 6] = s[3];
  a[r + 7] = s[4];
  a[r + 8] = s[5];
}

// (S v)_r for a symmetric block S (6 lower entries): einsum("ij,j->i") order.
template <class V>
AMS_HD void sym_matvec(const V s[6], const V w[3], V out[3]) {
  out[0] = s[0] * w[0] + s[1] * w[1] + s[3] * w[2];
  out[1] = s[1] * w[0] + s[2] * w[1] + s[4] * w[2];
  out[2] = s[3] * w[0] + s[4] * w[1] + s[5] * w[2];
}

// u uᵀ as 6 lower entries.
template <class V>
AMS_HD void outer6(const V u[3], V dd[6]) {
  dd[0] = u[0] * u[0];
  dd[1] = u[1] * u[0];
  dd[2] = u[1] * u[1];
  dd[3] = u[2] * u[0];
  dd[4] = u[2] * u[1];
  dd[5] = u[2] * u[2];
}

AMS_HD constexpr bool diag6(int e) { return e == 0 || e == 2 || e == 5; }

// Copy the lower triangle of every diagonal block to its upper triangle (the solver reads only
// the lower one; the assembled blocks returned for the parity tests are full).
template <class V, class T>
AMS_HD void mirror_blocks(const Lanes<V, T>& a, int64_t n) {
  for (int64_t i = 0; i < n; ++i) {
    const int64_t r = i * kRow;
    a[r + 1] = a[r + 3];
    a[r + 2] = a[r + 6];
    a[r + 5] = a[r + 7];
  }
}

// Springs between particles i and i + k (forces.spring_forces and the band of
// assembly.assemble_system). Pairs are visited along the k chains i ≡ c (mod k), from the tip
// down, so each row receives its lower pair (i, i+k) before its upper pair (i−k, i), as
// `diag + pad(hk, 0, k) + pad(hk, k, 0)` adds them, and its force (fp[i] − fp[i−k]) in one
// addition with both pair forces known.
template <int K, class V, class T>
AMS_HD void add_springs(const Strand<V, T>& s, T h2, bool geometric) {
  const int64_t n = s.n, pairs = n - K;
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  const Lanes<V, T>& kap = s.stiffness[K - 1];
  const Lanes<V, T>& len0 = s.rest_length[K - 1];
  for (int64_t c = 0; c < K && c < pairs; ++c) {
    V fnext[3] = {zero, zero, zero}; // force of pair i + K on its lower particle (0: no such pair)
    for (int64_t i = c + ((pairs - 1 - c) / K) * K; i >= c; i -= K) {
      V xi[3], xj[3], d[3], u[3], len;
      load3(s.x, i, xi);
      load3(s.x, i + K, xj);
      for (int q = 0; q < 3; ++q) d[q] = xj[q] - xi[q];
      safe_normalize(d, u, len, T(1e-20));
      const V kp = kap[i], l0 = len0[i];
      const V mag = kp * (len - l0);
      V fp[3], dd[6], hk[6];
      for (int q = 0; q < 3; ++q) fp[q] = mag * u[q];
      outer6(u, dd);
      if (geometric) { // (1 − l'/L)₊, l' = l (1 + 1e-6): no term within rounding of the rest length
        const V safe = select(len > T(0), len, one);
        const V slack = l0 * T(kGeometricSlack);
        const V g = select(len > slack, T(1) - slack / safe, zero);
        for (int e = 0; e < 6; ++e) dd[e] = dd[e] + g * (diag6(e) ? T(1) - dd[e] : -dd[e]);
      }
      for (int e = 0; e < 6; ++e) hk[e] = h2 * (kp * dd[e]);
      // upper end j = i + K: force, diagonal (its lower pair came first), band block
      const int64_t j = i + K;
      for (int q = 0; q < 3; ++q) s.force[3 * j + q] = s.force[3 * j + q] + (fnext[q] - fp[q]);
      add_diag(s.a, j, hk);
      V neg[6];
      for (int e = 0; e < 6; ++e) neg[e] = -hk[e];
      set_block(s.a, j, K, neg);
      // lower end i: diagonal (its upper pair comes next in this chain)
      add_diag(s.a, i, hk);
      for (int q = 0; q < 3; ++q) fnext[q] = fp[q];
    }
    for (int q = 0; q < 3; ++q) s.force[3 * c + q] = s.force[3 * c + q] + (fnext[q] - zero);
  }
}

// The non-Hookean curve (forces.integrity_elongation_law): φ and the tangent slope.
template <class V, class T>
AMS_HD void elongation_law(const V& e, const Material<T>& mat, V& phi, V& slope) {
  const T span = mat.breaking - mat.transition;
  const V zero = splat<V, T>(T(0));
  const V over = lane_max(e - mat.transition, zero);
  const V over_c = lane_min(over, splat<V, T>(span));
  const V below = lane_min(e, splat<V, T>(mat.transition));
  const T soft = T(1) - mat.soft_ratio;
  phi = below + over_c - soft * over_c * over_c / (T(2) * span);
  slope = T(1) - soft * over_c / span;
}

// The integrity spring of every particle (assembly._integrity_terms).
template <class V, class T>
AMS_HD void add_integrity(const Strand<V, T>& s, const Material<T>& mat, const FrameSettings& cfg, const T* pose_a,
                          T h2) {
  const int64_t n = s.n;
  const V one = splat<V, T>(T(1));
  for (int64_t i = 0; i < n; ++i) {
    V xi[3], y[3], w[3];
    load3(s.x, i, xi);
    load3(s.ghost, i, y);
    load3(s.ghost_velocity, i, w);
    const V kI = s.integrity[i];
    if (cfg.integrity_model == kIntegrityHookean) {
      const V hk = h2 * kI;
      for (int q = 0; q < 3; ++q) s.force[3 * i + q] = s.force[3 * i + q] + kI * (y[q] - xi[q]);
      const int64_t r = i * kRow;
      s.a[r + 0] = s.a[r + 0] + hk;
      s.a[r + 4] = s.a[r + 4] + hk;
      s.a[r + 8] = s.a[r + 8] + hk;
      for (int q = 0; q < 3; ++q) s.b[3 * i + q] = s.b[3 * i + q] + hk * w[q];
      continue;
    }
    // non-Hookean: anchor = ghost − sag offset (world), preload κ_I · offset
    V sag[3], off[3], d[3], u[3], dist;
    load3(s.sag_offset, i, sag);
    rotate(pose_a, sag, off);
    for (int q = 0; q < 3; ++q) d[q] = (y[q] - off[q]) - xi[q];
    safe_normalize(d, u, dist, T(1e-20));
    const V L = s.segment[i];
    const V e = dist / L;
    V phi, slope;
    elongation_law(e, mat, phi, slope);
    const V mag = kI * L * phi;
    for (int q = 0; q < 3; ++q) s.force[3 * i + q] = s.force[3 * i + q] + (kI * off[q] + mag * u[q]);
    const auto stretched = e > T(0);
    const V secant = select(stretched, phi / select(stretched, e, one), one);
    V dd[6], ht[6], gv[3];
    outer6(u, dd);
    for (int e6 = 0; e6 < 6; ++e6)
      ht[e6] = h2 * (kI * (slope * dd[e6] + secant * (diag6(e6) ? T(1) - dd[e6] : -dd[e6])));
    add_diag(s.a, i, ht);
    sym_matvec(ht, w, gv);
    for (int q = 0; q < 3; ++q) s.b[3 * i + q] = s.b[3 * i + q] + gv[q];
  }
}

// The angular spring of every segment (forces.angular_force, assembly._angular_terms), from the
// tip down so that each particle's two segment contributions are added in torch's order.
template <class V, class T>
AMS_HD void add_angular(const Strand<V, T>& s, const FrameSettings& cfg, T h2) {
  const int64_t n = s.n;
  const V zero = splat<V, T>(T(0)), one = splat<V, T>(T(1));
  V fnext[3] = {zero, zero, zero}, gnext[3] = {zero, zero, zero}; // segment i + 1's force and ghost term
  for (int64_t i = n - 2; i >= 0; --i) {
    V x0[3], x1[3], y0[3], y1[3], e[3], g[3], eh[3], gh[3], elen, glen;
    load3(s.x, i, x0);
    load3(s.x, i + 1, x1);
    load3(s.ghost, i, y0);
    load3(s.ghost, i + 1, y1);
    for (int q = 0; q < 3; ++q) {
      e[q] = x1[q] - x0[q];
      g[q] = y1[q] - y0[q];
    }
    safe_normalize(e, eh, elen, T(1e-20));
    safe_normalize(g, gh, glen, T(1e-20));
    const V cs = eh[0] * gh[0] + eh[1] * gh[1] + eh[2] * gh[2];
    V perp[3], th[3], sn;
    for (int q = 0; q < 3; ++q) perp[q] = gh[q] - eh[q] * cs;
    safe_normalize(perp, th, sn, T(1e-24));
    const V theta = lane_atan2<V, T>(sn, cs);
    const V kA = s.angular[i];
    const V mag = kA * theta;
    V f[3];
    for (int q = 0; q < 3; ++q) f[q] = mag * th[q];
    const int64_t j = i + 1;
    for (int q = 0; q < 3; ++q) {
      const V add = cfg.angular_reaction ? f[q] - fnext[q] : f[q];
      s.force[3 * j + q] = s.force[3 * j + q] + add;
      fnext[q] = f[q];
    }
    if (!cfg.implicit_angular) continue;
    const auto positive = elen > T(0);
    const V inv_len = select(positive, T(1) / select(positive, elen, one), zero);
    const V coef = kA * inv_len;
    V ee[6], ht[6];
    outer6(eh, ee);
    for (int e6 = 0; e6 < 6; ++e6) ht[e6] = h2 * (coef * (diag6(e6) ? T(1) - ee[e6] : -ee[e6]));
    V w0[3], w1[3], dw[3], gv[3];
    load3(s.ghost_velocity, i, w0);
    load3(s.ghost_velocity, j, w1);
    for (int q = 0; q < 3; ++q) dw[q] = w1[q] - w0[q];
    if (cfg.angular_reaction) {
      add_diag(s.a, i, ht); // segment i is particle i's lower segment: it comes first
      add_diag(s.a, j, ht);
      const int64_t r = j * kRow + 9;
      V blk[6] = {s.a[r + 0], s.a[r + 3], s.a[r + 4], s.a[r + 6], s.a[r + 7], s.a[r + 8]};
      for (int e6 = 0; e6 < 6; ++e6) blk[e6] = blk[e6] - ht[e6];
      set_block(s.a, j, 1, blk);
      sym_matvec(ht, dw, gv);
      for (int q = 0; q < 3; ++q) {
        s.b[3 * j + q] = s.b[3 * j + q] + (gv[q] - gnext[q]);
        gnext[q] = gv[q];
      }
    } else {
      add_diag(s.a, j, ht);
      V vi[3], rel[3];
      load3(s.v, i, vi);
      for (int q = 0; q < 3; ++q) rel[q] = vi[q] + dw[q];
      sym_matvec(ht, rel, gv);
      for (int q = 0; q < 3; ++q) s.b[3 * j + q] = s.b[3 * j + q] + gv[q];
    }
  }
  if (cfg.angular_reaction) {
    for (int q = 0; q < 3; ++q) s.force[q] = s.force[q] + (zero - fnext[q]);
    if (cfg.implicit_angular)
      for (int q = 0; q < 3; ++q) s.b[q] = s.b[q] + (zero - gnext[q]);
  }
}

// Pinned rows (assembly._pinned_rows): prescribed velocities v_pin = (target − x)/Δt' of the
// pinned particles (target = R_b X̄ + t_b), rhs −= A v_pin over pinned columns on free rows,
// pinned rows m I v = m v_pin, free rows lose their pinned columns. Only rows < pinned_max + 3
// are touched. Leaves v_pin in `force` and the targets in `ghost` (pinned rows only).
template <class V, class T>
AMS_HD void pin_rows(const Strand<V, T>& s, const T* pose_b, T h) {
  const int64_t n = s.n;
  const V zero = splat<V, T>(T(0));
  const int64_t pinned_rows = s.pinned_max < n ? s.pinned_max : n;
  for (int64_t i = 0; i < pinned_rows; ++i) {
    V r[3], tg[3], xi[3];
    load3(s.rest, i, r);
    rigid_map(pose_b, pose_b + 9, r, tg);
    load3(s.x, i, xi);
    const auto pin_i = T(i) < s.pinned;
    for (int q = 0; q < 3; ++q) s.force[3 * i + q] = select(pin_i, (tg[q] - xi[q]) / h, zero);
    store3(s.ghost, i, tg);
  }
  const int64_t rows = s.pinned_max + 3 < n ? s.pinned_max + 3 : n;
  for (int64_t i = 0; i < rows; ++i) {
    const auto pin_i = T(i) < s.pinned;
    V y[3] = {zero, zero, zero};
    for (int k = 1; k <= 3; ++k) {
      const int64_t j = i - k;
      if (j < 0 || j >= pinned_rows) continue; // v_pin is 0 there: A v_pin adds exact zeros
      const int64_t blk = i * kRow + 9 * k;
      V vp[3], t[3];
      load3(s.force, j, vp);
      for (int q = 0; q < 3; ++q) t[q] = s.a[blk + 3 * q + 0] * vp[0] + s.a[blk + 3 * q + 1] * vp[1] + s.a[blk + 3 * q + 2] * vp[2];
      for (int q = 0; q < 3; ++q) y[q] = y[q] + t[q];
    }
    const V m = s.mass[i];
    for (int q = 0; q < 3; ++q) {
      const V rhs = s.b[3 * i + q];
      s.b[3 * i + q] = select(pin_i, m * s.force[3 * i + q], rhs - y[q]);
    }
    const int64_t r0 = i * kRow;
    for (int e = 0; e < 9; ++e) s.a[r0 + e] = select(pin_i, (e % 4 == 0) ? m : zero, s.a[r0 + e]);
    for (int k = 1; k <= 3; ++k) {
      const auto keep = T(i - k) >= s.pinned; // free column (row i free too: the prefix is pinned)
      const int64_t blk = i * kRow + 9 * k;
      for (int e = 0; e < 9; ++e) s.a[blk + e] = select(keep, s.a[blk + e], zero);
    }
  }
}

// Assemble substep k's system (assembly.assemble_system) from the state in s.x, s.v, between
// the head poses pose_a and pose_b (kPoseElems each), into s.a and s.b.
template <class V, class T>
AMS_HD void assemble(const Strand<V, T>& s, const Material<T>& mat, const FrameSettings& cfg, const T* pose_a,
                     const T* pose_b) {
  const int64_t n = s.n;
  const double hd = cfg.dt / cfg.substeps;
  const T h = T(hd), h2 = T(hd * hd);
  const V zero = splat<V, T>(T(0));
  for (int64_t i = 0; i < n; ++i) {
    V g[3], ya[3], yb[3], vi[3];
    load3(s.ghost_rest, i, g);
    rigid_map(pose_a, pose_a + 9, g, ya);
    rigid_map(pose_b, pose_b + 9, g, yb);
    store3(s.ghost, i, ya);
    for (int q = 0; q < 3; ++q) s.ghost_velocity[3 * i + q] = (yb[q] - ya[q]) / h;
    const V m = s.mass[i];
    const V md = m + h * s.drag[i];
    const int64_t r = i * kRow;
    for (int e = 0; e < kRow; ++e) s.a[r + e] = zero;
    s.a[r + 0] = md;
    s.a[r + 4] = md;
    s.a[r + 8] = md;
    load3(s.v, i, vi);
    for (int q = 0; q < 3; ++q) {
      V f = m * mat.gravity[q];
      if (s.has_ext) f = f + s.ext[3 * i + q];
      s.force[3 * i + q] = f;
      s.b[3 * i + q] = m * vi[q];
    }
  }
  add_springs<1>(s, h2, cfg.geometric_stiffness);
  add_springs<2>(s, h2, cfg.geometric_stiffness);
  add_springs<3>(s, h2, cfg.geometric_stiffness);
  if (cfg.integrity_model != kIntegrityNone) add_integrity(s, mat, cfg, pose_a, h2);
  if (cfg.angular) add_angular(s, cfg, h2);
  for (int64_t e = 0; e < 3 * n; ++e) s.b[e] = s.b[e] + h * s.force[e];
  pin_rows(s, pose_b, h);
}

// One substep: assemble, solve, advance the positions (pinned particles onto their targets).
template <class V, class T>
AMS_HD void advance(const Strand<V, T>& s, const Material<T>& mat, const FrameSettings& cfg, const T* pose_a,
                    const T* pose_b) {
  assemble(s, mat, cfg, pose_a, pose_b);
  banded::solve_strand<V, T>(s.a, s.b, s.n);
  const T h = T(cfg.dt / cfg.substeps);
  for (int64_t i = 0; i < s.n; ++i) {
    const bool maybe_pinned = i < s.pinned_max;
    const auto pin_i = T(i) < s.pinned;
    for (int q = 0; q < 3; ++q) {
      const V vn = s.b[3 * i + q];
      const V moved = s.x[3 * i + q] + h * vn;
      s.x[3 * i + q] = maybe_pinned ? select(pin_i, s.ghost[3 * i + q], moved) : moved;
      s.v[3 * i + q] = vn;
    }
  }
}

// The colliders of substep contact, as given to the kernel: each collider's world pose arrays
// hold one pose per substep, (M, P, ...) with P = 1 or the number of scenes (the world pose at
// the end of substep k first); geometry and the rest as collide::ColliderArgs.
template <class T>
struct ContactArgs {
  int count; // 0: no substep contact
  collide::ColliderArgs<T> colliders[collide::kMaxColliders];
};

// Collider c of substep k: its arguments with the pose pointers moved to that substep's poses.
template <class T>
AMS_HD collide::ColliderArgs<T> contact_collider(const ContactArgs<T>& a, int c, int k) {
  collide::ColliderArgs<T> out = a.colliders[c];
  const int64_t p = out.pose_scenes;
  out.rotation += 9 * p * k;
  out.translation += 3 * p * k;
  out.linear_velocity += 3 * p * k;
  out.angular_velocity += 3 * p * k;
  return out;
}

// The whole frame of one strand: M substeps, then follow-the-leader. `poses`: this scene's
// M + 1 substep poses (kPoseElems each, from substep_pose). `contact`: substep contact, this
// scene's prepared colliders substep-major (contact[k · contact_count + c]), or none.
template <class V, class T>
AMS_HD void strand_frame(const Strand<V, T>& s, const Material<T>& mat, const FrameSettings& cfg, const T* poses,
                         const collide::Prepared<T>* contact = nullptr, int contact_count = 0) {
  const T h = T(cfg.dt / cfg.substeps);
  for (int k = 0; k < cfg.substeps; ++k) {
    advance(s, mat, cfg, poses + kPoseElems * k, poses + kPoseElems * (k + 1));
    if (contact_count > 0) collide::collide_strand(s.x, s.v, s.n, s.pinned, contact + k * contact_count, contact_count, h);
  }
  if (cfg.inextensibility)
    follow_the_leader(s.x, s.v, s.rest, s.rest_length[0], s.pinned, poses + kPoseElems * cfg.substeps,
                      T(cfg.ftl_damping), T(cfg.dt), s.n);
}

} // namespace frame
} // namespace ams_torch
