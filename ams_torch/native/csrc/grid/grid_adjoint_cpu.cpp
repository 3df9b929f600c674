// CPU kernels of the hair–hair grid's adjoints: ops `ams_torch_cpu::{p2g_adjoint, pressure_adjoint,
// g2p_adjoint}` (arithmetic in grid_adjoint.h; the definition is sparse.py differentiated by
// autograd). Shapes:
//   p2g_adjoint(xl, vl (B, P, 3), m (B, P), origin (3,), table (B, nb^3) int32, g_faces (B, K, 3, 64, 2),
//               cell_size, resolution) -> g_xl, g_vl (B, P, 3), g_m (B, P)
//   g2p_adjoint(xl, vl (B, P, 3), field (B, K, 3, 64), table, origin, g_dv (B, P, 3), cell_size,
//               resolution, pic) -> g_xl, g_vl (B, P, 3), g_field (B, K, 3, 64), dv (B, P, 3)
//   pressure_adjoint(faces, table, blocks, count, target, dt, cell_size, resolution, iterations,
//                    omega, stiffness, pic, g_field (B, K, 3, 64)) -> g_faces (B, K, 3, 64, 2)
// xl, vl are head-frame positions and velocities relative to the grid's motion (transfer.to_head);
// g_dv the adjoint of G2P's head-frame change (zero for pinned particles); dv that change, as the
// forward computes it (for the adjoint of the frame rotation, taken by the caller).
//
// Parallelism, chosen so that results do not depend on the thread count:
//   * p2g_adjoint: a gather per particle (parallel over particles);
//   * g2p_adjoint: each particle scatters into g_field: particles bucketed by x-slab of the grid and
//     slabs scattered in two colours, as the forward P2G (grid_cpu.cpp), so every face sums its
//     contributions in one fixed order;
//   * pressure_adjoint: recomputes the forward on the used slots (cell entries, the list of active
//     cells in pool order: the torch path's list, every active cell), the sweeps keeping φ before
//     each (sweeps_cpu.h), then in reverse: the face field's adjoint gathered into each active cell's
//     φ̄, the sweeps reversed, each active cell's entry differentiated (12 face adjoints kept per
//     cell), and every face gathers its adjoints from the field and from the (at most two) cells
//     that read it, per used slot in parallel. The active cells beyond the torch path's capacity
//     (an overflow the forward reports) are differentiated as the kernels ran them.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <tuple>
#include <vector>

#include "grid/bits.h"
#include "grid/grid.h"
#include "grid/grid_adjoint.h"
#include "grid/grid_adjoint_binding.h"
#include "grid/grid_simd.h"
#include "grid/sweeps_cpu.h"

namespace ams_torch {
namespace grid {
namespace {

constexpr int64_t kParticleGrain = 512;
constexpr int64_t kSlotGrain = 16;
constexpr int64_t kSlab = 4; // cells per x-slab of the scatter's colouring (as grid_cpu.cpp)


void check_float(const char* op, const at::Tensor& t, const char* name, at::ScalarType dtype) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == dtype, "ams_torch_cpu::", op, ": ", name,
              " must be a CPU ", dtype, " tensor, got ", t.scalar_type(), " on ", t.device());
}

void check_shape(const char* op, const at::Tensor& t, const char* name, at::IntArrayRef sizes) {
  TORCH_CHECK(t.sizes() == sizes, "ams_torch_cpu::", op, ": ", name, " must be ", sizes, ", got ", t.sizes());
}

void check_table(const char* op, const at::Tensor& t, const char* name, at::IntArrayRef sizes) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kInt && t.sizes() == sizes, "ams_torch_cpu::", op,
              ": ", name, " must be a CPU int32 tensor of shape ", sizes, ", got ", t.scalar_type(), " ", t.sizes());
}

// The checks shared by the particle adjoints; returns (B, P, nb).
std::tuple<int64_t, int64_t, int64_t> check_particle_args(const char* op, const at::Tensor& xl, const at::Tensor& vl,
                                                          const at::Tensor& origin, const at::Tensor& table,
                                                          double cell_size, int64_t r) {
  TORCH_CHECK(xl.dim() == 3 && xl.size(2) == 3, "ams_torch_cpu::", op, ": xl must be (B, P, 3), got ", xl.sizes());
  const auto dtype = xl.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "ams_torch_cpu::", op, ": float32 or float64 only");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cpu::", op, ": need resolution >= 2 and cell_size > 0");
  check_float(op, xl, "xl", dtype);
  check_float(op, vl, "vl", dtype);
  check_shape(op, vl, "vl", xl.sizes());
  check_float(op, origin, "origin", dtype);
  check_shape(op, origin, "origin", {3});
  const int64_t B = xl.size(0), P = xl.size(1), nb = blocks_per_axis(r);
  TORCH_CHECK(P < (int64_t(1) << 31), "ams_torch_cpu::", op, ": at most 2^31 - 1 particles per scene");
  check_table(op, table, "table", {B, nb * nb * nb});
  return {B, P, nb};
}

// ---- P2G --------------------------------------------------------------------------------------
#if AMS_GRID_SIMD
// Particles [q0, q0 + n) of one scene (n <= W) in SIMD lanes: grid_adjoint.h's p2g_particle_adjoint
// lane by lane (grid_simd.h's stencils; the same operations in the same order).
template <class T>
void p2g_adjoint_batch(const T* xl, const T* vl, const T* m, const T* origin, T h, int64_t r, int64_t nb,
                       const int32_t* table, const T* g_faces, int64_t q0, int n, T* g_xl, T* g_vl, T* g_m) {
  using V = simd::VecT<T>;
  using I = simd::IntT<T>;
  constexpr int W = simd::Lanes<T>::W;
  V x[3], v[3], mm;
  for (int lane = 0; lane < W; ++lane) {
    const int64_t q = q0 + (lane < n ? lane : n - 1);
    for (int a = 0; a < 3; ++a) {
      x[a][lane] = xl[3 * q + a];
      v[a][lane] = vl[3 * q + a];
    }
    mm[lane] = m[q];
  }
  simd::Batch<T> bt;
  simd::batch_stencil<T>(x, origin, h, r, nb, table, n, bt);
  V g1[2][3][2] = {};
  V gm = V{}, gv[3];
  for (int c = 0; c < 3; ++c) {
    V gw[8];
    V gmom = V{};
    const V mvc = mm * v[c];
    for (int k = 0; k < 8; ++k) {
      const I f = bt.face[c][k];
      const I use = f >= 0;
      const I at2 = (use ? f : I{}) * 2;
      const V gmass = simd::gather(g_faces, at2, use);
      const V gp = simd::gather(g_faces + 1, at2, use);
      gw[k] = mm * gmass + mvc * gp;
      gm = gm + bt.w[c][k] * gmass;
      gmom = gmom + bt.w[c][k] * gp;
    }
    gm = gm + gmom * v[c];
    gv[c] = gmom * mm;
    simd::corner_weights_adjoint_rt<T>(c, bt.wv, gw, g1);
  }
  V gx[3];
  simd::position_adjoint<T>(x, origin, h, r, g1, gx);
  for (int lane = 0; lane < n; ++lane) {
    const int64_t q = q0 + lane;
    for (int a = 0; a < 3; ++a) {
      g_xl[3 * q + a] = gx[a][lane];
      g_vl[3 * q + a] = gv[a][lane];
    }
    g_m[q] = gm[lane];
  }
}
#endif

template <class T>
void p2g_adjoint_impl(const T* xl, const T* vl, const T* m, const T* origin, const int32_t* table, const T* g_faces,
                      T* g_xl, T* g_vl, T* g_m, int64_t B, int64_t P, int64_t r, int64_t K, double cell_size) {
  const T h = T(cell_size);
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
#if AMS_GRID_SIMD
  constexpr int W = simd::Lanes<T>::W;
  const int64_t batches = (P + W - 1) / W;
  at::parallel_for(0, B * batches, kParticleGrain / W, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t b = t / batches, first = (t % batches) * W;
      p2g_adjoint_batch(xl + 3 * b * P, vl + 3 * b * P, m + b * P, origin, h, r, nb, table + b * nb3,
                        g_faces + b * K * 3 * kBlockCells * 2, first, int(std::min<int64_t>(W, P - first)),
                        g_xl + 3 * b * P, g_vl + 3 * b * P, g_m + b * P);
    }
  });
#else
  at::parallel_for(0, B * P, kParticleGrain, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t b = i / P;
      p2g_particle_adjoint(xl + 3 * i, vl + 3 * i, m[i], origin, h, r, nb, table + b * nb3,
                           g_faces + b * K * 3 * kBlockCells * 2, g_xl + 3 * i, g_vl + 3 * i, g_m + i);
    }
  });
#endif
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> p2g_adjoint_cpu(const at::Tensor& xl, const at::Tensor& vl,
                                                               const at::Tensor& m, const at::Tensor& origin,
                                                               const at::Tensor& table, const at::Tensor& g_faces,
                                                               double cell_size, int64_t resolution) {
  constexpr const char* op = "p2g_adjoint";
  const auto [B, P, nb] = check_particle_args(op, xl, vl, origin, table, cell_size, resolution);
  const auto dtype = xl.scalar_type();
  check_float(op, m, "m", dtype);
  check_shape(op, m, "m", {B, P});
  check_float(op, g_faces, "g_faces", dtype);
  TORCH_CHECK(g_faces.dim() == 5 && g_faces.size(0) == B && g_faces.size(2) == 3 && g_faces.size(3) == kBlockCells &&
                  g_faces.size(4) == 2,
              "ams_torch_cpu::p2g_adjoint: g_faces must be (B, K, 3, 64, 2), got ", g_faces.sizes());
  const int64_t K = g_faces.size(1);
  at::Tensor g_xl = at::empty({B, P, 3}, xl.options()), g_vl = at::empty({B, P, 3}, xl.options());
  at::Tensor g_m = at::empty({B, P}, xl.options());
  if (B * P == 0) return {g_xl, g_vl, g_m};
  const at::Tensor xc = xl.contiguous(), vc = vl.contiguous(), mc = m.contiguous(), oc = origin.contiguous(),
                   tc = table.contiguous(), gc = g_faces.contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "ams_torch_cpu::p2g_adjoint", [&] {
    p2g_adjoint_impl<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                               mc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(),
                               tc.const_data_ptr<int32_t>(), gc.const_data_ptr<scalar_t>(),
                               g_xl.mutable_data_ptr<scalar_t>(), g_vl.mutable_data_ptr<scalar_t>(),
                               g_m.mutable_data_ptr<scalar_t>(), B, P, resolution, K, cell_size);
  });
  return {g_xl, g_vl, g_m};
}

// ---- G2P --------------------------------------------------------------------------------------
#if AMS_GRID_SIMD
// The particles order[0, n) (n <= W, indices within one scene) in SIMD lanes: grid_adjoint.h's
// g2p_particle_adjoint lane by lane (the same operations in the same order); the scatter into the
// field's adjoint particle after particle, as the scalar loop.
template <class T>
void g2p_adjoint_batch(const T* xl, const T* vl, const T* field, const T* origin, T h, int64_t r, int64_t nb,
                       const int32_t* table, T pic, const T* g_dv, const int32_t* order, int n, T* g_xl, T* g_vl,
                       T* dv, T* g_field) {
  using V = simd::VecT<T>;
  using I = simd::IntT<T>;
  constexpr int W = simd::Lanes<T>::W;
  V x[3], v[3], g[3];
  for (int lane = 0; lane < W; ++lane) {
    const int64_t q = order[lane < n ? lane : n - 1];
    for (int a = 0; a < 3; ++a) {
      x[a][lane] = xl[3 * q + a];
      v[a][lane] = vl[3 * q + a];
      g[a][lane] = g_dv[3 * q + a];
    }
  }
  simd::Batch<T> bt;
  simd::batch_stencil<T>(x, origin, h, r, nb, table, n, bt);
  V g1[2][3][2] = {};
  V d[3], gv[3];
  for (int c = 0; c < 3; ++c) {
    V gw[8];
    V ws = V{}, acc = V{};
    for (int k = 0; k < 8; ++k) {
      const I f = bt.face[c][k];
      const I use = f >= 0;
      const V fv = simd::gather(field, use ? f : I{}, use);
      acc = acc + fv * bt.w[c][k];
      gw[k] = g[c] * fv - pic * g[c] * v[c];
      ws = ws + bt.w[c][k];
    }
    d[c] = acc - pic * ws * v[c];
    gv[c] = -(pic * ws) * g[c];
    simd::corner_weights_adjoint_rt<T>(c, bt.wv, gw, g1);
  }
  V gx[3];
  simd::position_adjoint<T>(x, origin, h, r, g1, gx);
  for (int lane = 0; lane < n; ++lane) {
    const int64_t q = order[lane];
    for (int a = 0; a < 3; ++a) {
      g_xl[3 * q + a] = gx[a][lane];
      g_vl[3 * q + a] = gv[a][lane];
      dv[3 * q + a] = d[a][lane];
    }
    for (int c = 0; c < 3; ++c)
      for (int k = 0; k < 8; ++k) {
        const auto f = bt.face[c][k][lane];
        if (f >= 0) g_field[f] += g[c][lane] * bt.w[c][k][lane];
      }
  }
}
#endif

template <class T>
void g2p_adjoint_impl(const T* xl, const T* vl, const T* field, const int32_t* table, const T* origin, const T* g_dv,
                      T* g_xl, T* g_vl, T* g_field, T* dv, int64_t B, int64_t P, int64_t r, int64_t K,
                      double cell_size, double pic) {
  const T h = T(cell_size), pict = T(pic);
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  const int64_t pool = K * 3 * kBlockCells;
  const int64_t slabs = (r + kSlab - 1) / kSlab;
  // bucket each scene's particles by x-slab (stable counting sort)
  std::vector<int32_t> slab(size_t(B * P)), order(size_t(B * P));
  std::vector<int64_t> start(size_t(B * (slabs + 1)), 0);
  at::parallel_for(0, B * P, kParticleGrain * 8, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      T c = grid_floor(cell_coord(xl + 3 * i, origin, h, 0));
      if (!(c >= T(0))) c = T(0); // also NaN
      if (c > T(r - 1)) c = T(r - 1);
      slab[size_t(i)] = int32_t(int64_t(c) / kSlab);
    }
  });
  for (int64_t b = 0; b < B; ++b) {
    int64_t* st = start.data() + b * (slabs + 1);
    for (int64_t p = 0; p < P; ++p) ++st[slab[size_t(b * P + p)] + 1];
    for (int64_t s = 0; s < slabs; ++s) st[s + 1] += st[s];
    std::vector<int64_t> fill(st, st + slabs);
    for (int64_t p = 0; p < P; ++p) order[size_t(b * P + fill[slab[size_t(b * P + p)]]++)] = int32_t(p);
  }
  for (int64_t colour = 0; colour < 2; ++colour) {
    const int64_t per_scene = (slabs - colour + 1) / 2;
    at::parallel_for(0, B * per_scene, 1, [&](int64_t t0, int64_t t1) {
      for (int64_t t = t0; t < t1; ++t) {
        const int64_t b = t / per_scene;
        const int64_t s = colour + 2 * (t % per_scene);
        const int64_t* st = start.data() + b * (slabs + 1);
        T* gf = g_field + b * pool;
#if AMS_GRID_SIMD
        constexpr int W = simd::Lanes<T>::W;
        for (int64_t q = st[s]; q < st[s + 1]; q += W)
          g2p_adjoint_batch(xl + 3 * b * P, vl + 3 * b * P, field + b * pool, origin, h, r, nb, table + b * nb3, pict,
                            g_dv + 3 * b * P, order.data() + b * P + q, int(std::min<int64_t>(W, st[s + 1] - q)),
                            g_xl + 3 * b * P, g_vl + 3 * b * P, dv + 3 * b * P, gf);
#else
        const auto add = [gf](int32_t f, T value) { gf[f] += value; };
        for (int64_t q = st[s]; q < st[s + 1]; ++q) {
          const int64_t i = b * P + order[size_t(b * P + q)];
          g2p_particle_adjoint(xl + 3 * i, vl + 3 * i, field + b * pool, origin, h, r, nb, table + b * nb3, pict,
                               g_dv + 3 * i, g_xl + 3 * i, g_vl + 3 * i, dv + 3 * i, add);
        }
#endif
      }
    });
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> g2p_adjoint_cpu(
    const at::Tensor& xl, const at::Tensor& vl, const at::Tensor& field, const at::Tensor& table,
    const at::Tensor& origin, const at::Tensor& g_dv, double cell_size, int64_t resolution, double pic) {
  constexpr const char* op = "g2p_adjoint";
  const auto [B, P, nb] = check_particle_args(op, xl, vl, origin, table, cell_size, resolution);
  const auto dtype = xl.scalar_type();
  check_float(op, field, "field", dtype);
  TORCH_CHECK(field.dim() == 4 && field.size(0) == B && field.size(2) == 3 && field.size(3) == kBlockCells,
              "ams_torch_cpu::g2p_adjoint: field must be (B, K, 3, 64), got ", field.sizes());
  check_float(op, g_dv, "g_dv", dtype);
  check_shape(op, g_dv, "g_dv", xl.sizes());
  const int64_t K = field.size(1);
  at::Tensor g_xl = at::empty({B, P, 3}, xl.options()), g_vl = at::empty({B, P, 3}, xl.options());
  at::Tensor g_field = at::zeros({B, K, 3, kBlockCells}, xl.options()), dv = at::empty({B, P, 3}, xl.options());
  if (B * P == 0) return {g_xl, g_vl, g_field, dv};
  const at::Tensor xc = xl.contiguous(), vc = vl.contiguous(), fc = field.contiguous(), tc = table.contiguous(),
                   oc = origin.contiguous(), gc = g_dv.contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "ams_torch_cpu::g2p_adjoint", [&] {
    g2p_adjoint_impl<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                               fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(),
                               oc.const_data_ptr<scalar_t>(), gc.const_data_ptr<scalar_t>(),
                               g_xl.mutable_data_ptr<scalar_t>(), g_vl.mutable_data_ptr<scalar_t>(),
                               g_field.mutable_data_ptr<scalar_t>(), dv.mutable_data_ptr<scalar_t>(), B, P, resolution,
                               K, cell_size, pic);
  });
  return {g_xl, g_vl, g_field, dv};
}

// ---- pressure ---------------------------------------------------------------------------------
template <class T>
void pressure_adjoint_impl(const T* faces, const int32_t* table, const int32_t* blocks, const int32_t* count, T rho0,
                           T dt, const T* g_field, T* g_faces, int64_t B, int64_t r, int64_t K, double cell_size,
                           int64_t iterations, double omega, double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(cell_size, rho0, dt, omega, stiffness, pic);
  const int64_t nb = blocks_per_axis(r), nb3 = nb * nb * nb;
  const int64_t pool = K * 3 * kBlockCells; // faces of one scene
  std::vector<int32_t> scene; // the used slots of every scene, numbered u = first[b] + slot
  const std::vector<int64_t> first = used_slots(count, B, K, &scene);
  const int64_t U = first[B];
  if (U == 0) return;
  std::vector<int32_t> nbr(size_t(U * 6));
  std::vector<uint64_t> active(static_cast<size_t>(U), 0);
  std::vector<T> entries(size_t(iterations > 0 ? U * kBlockCells * kEntry : 0));
  at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
    for (int64_t u = u0; u < u1; ++u) {
      const int64_t b = scene[u], slot = u - first[b];
      int32_t* nu = nbr.data() + 6 * u;
      slot_neighbours(blocks[b * K + slot], nb, table + b * nb3, nu);
      if (iterations == 0) continue;
      const T* fs = faces + b * pool * 2;
      uint64_t bits = 0;
      for (int l = 0; l < kBlockCells; ++l)
        if (cell_entry(fs, slot, l, nu, q, entries.data() + (u * kBlockCells + l) * kEntry)) bits |= uint64_t(1) << l;
      active[u] = bits;
    }
  });
  // The sweeps' adjoint only moves where a sweep's input is >= 0: the slots the forward sweeps
  // (grid_cpu.cpp's "awake" slots: those with a cell whose src >= 0, here ties included since the
  // clamp passes the gradient at 0, then the neighbours of every slot whose phi became non-zero).
  // Anywhere else every update is max(0, src < 0) = 0 from zero neighbours, whose adjoint is 0.
  std::vector<uint64_t> listed(static_cast<size_t>(U), 0);
  if (iterations > 0) {
    std::vector<uint8_t> awake(static_cast<size_t>(U), 0);
    for (int64_t u = 0; u < U; ++u)
      for (uint64_t bits = active[u]; bits && !awake[u]; bits &= bits - 1)
        awake[u] = entries[size_t((u * kBlockCells + lowest_bit(bits)) * kEntry)] >= T(0);
    std::vector<int64_t> wake;
    for (int64_t u = 0; u < U; ++u)
      if (awake[u]) wake.push_back(u);
    std::vector<T> pa(size_t(B * K * kBlockCells), T(0)), pb(size_t(B * K * kBlockCells), T(0));
    std::vector<uint8_t> live(static_cast<size_t>(U), 0);
    for (int64_t it = 0; it < iterations && !wake.empty(); ++it) {
      const T* src = it % 2 == 0 ? pa.data() : pb.data();
      T* dst = it % 2 == 0 ? pb.data() : pa.data();
      const int64_t n = int64_t(wake.size());
      at::parallel_for(0, n, kSlotGrain, [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i) {
          const int64_t u = wake[size_t(i)], b = scene[u], slot = u - first[b];
          bool any = false;
          for (uint64_t bits = active[u]; bits; bits &= bits - 1) {
            const int l = lowest_bit(bits);
            const T t = sweep_cell(src + b * K * kBlockCells, slot, l, nbr.data() + 6 * u,
                                   entries.data() + (u * kBlockCells + l) * kEntry, q.one_minus_omega);
            dst[(b * K + slot) * kBlockCells + l] = t;
            any = any || t != T(0);
          }
          live[u] = any;
        }
      });
      wake_neighbours(wake, n, live, awake, nbr.data(), first.data(), scene.data());
    }
    for (int64_t u = 0; u < U; ++u) listed[u] = awake[u] ? active[u] : 0;
  }
  // list of those slots' active cells in pool order: list index of (u, l) = off[u] + rank of l in listed[u]
  std::vector<int64_t> off(size_t(U + 1), 0);
  for (int64_t u = 0; u < U; ++u) off[u + 1] = off[u] + popcount(listed[u]);
  const int64_t A = off[U], n1 = A + 1; // slot A: a zero that stays zero
  const auto list_index = [&](int64_t u, int l) -> int64_t {
    const uint64_t bits = listed[u];
    if (!((bits >> l) & 1)) return -1;
    return off[u] + popcount(bits & ((uint64_t(1) << l) - 1));
  };
  std::vector<T> phi_pool(size_t(B * K * kBlockCells), T(0)); // φ on the used slots (0 off the active cells)
  std::vector<T> cell_g(size_t(A * 12)); // per active cell: adjoints of its six faces' mass, then momentum
  if (A > 0 && iterations > 0) {
    std::vector<T> src(size_t(n1), T(0)), coef(size_t(n1), T(0)), w(size_t(6 * n1), T(0));
    std::vector<int64_t> lnbr(size_t(6 * n1), A);
    at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
      for (int64_t u = u0; u < u1; ++u) {
        const int64_t b = scene[u], slot = u - first[b];
        for (uint64_t bits = listed[u]; bits; bits &= bits - 1) {
          const int l = lowest_bit(bits);
          const int64_t i = list_index(u, l);
          const T* e = entries.data() + (u * kBlockCells + l) * kEntry;
          src[size_t(i)] = e[0];
          coef[size_t(i)] = e[1];
          for (int d = 0; d < 6; ++d) {
            w[size_t(d * n1 + i)] = e[2 + d];
            int64_t s;
            const int nl = neighbour_cell(l, d, slot, nbr.data() + 6 * u, &s);
            const int64_t j = s < 0 ? -1 : list_index(first[b] + s, nl);
            lnbr[size_t(d * n1 + i)] = j < 0 ? A : j;
          }
        }
      }
    });
    std::vector<T> history(static_cast<size_t>(iterations * n1)), phi_l(static_cast<size_t>(n1));
    host_sweeps::forward<T>(src.data(), coef.data(), w.data(), lnbr.data(), n1, iterations, q.one_minus_omega,
                           history.data(), phi_l.data());
    // φ̄ of every active cell from the face field: its lower c-faces (φ_hi there) and upper c-faces
    // (the next cell's lower faces: φ_lo there)
    std::vector<T> g_phi(size_t(n1), T(0));
    at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
      for (int64_t u = u0; u < u1; ++u) {
        const int64_t b = scene[u], slot = u - first[b];
        const T* fs = faces + b * pool * 2;
        const T* gfs = g_field + b * pool;
        T* ps = phi_pool.data() + b * K * kBlockCells;
        for (uint64_t bits = listed[u]; bits; bits &= bits - 1) {
          const int l = lowest_bit(bits);
          const int64_t i = list_index(u, l);
          ps[slot * kBlockCells + l] = phi_l[size_t(i)];
          T acc = T(0);
          for (int c = 0; c < 3; ++c) {
            acc = acc + face_phi_adjoint(fs, gfs, slot, c, l, q);
            int64_t up_slot;
            const int up = neighbour_cell(l, 2 * c + 1, slot, nbr.data() + 6 * u, &up_slot);
            if (up_slot >= 0) acc = acc - face_phi_adjoint(fs, gfs, up_slot, c, up, q);
          }
          g_phi[size_t(i)] = acc;
        }
      }
    });
    std::vector<T> g_src(size_t(n1), T(0)), g_coef(size_t(n1), T(0)), g_w(size_t(6 * n1), T(0));
    host_sweeps::reverse<T>(src.data(), coef.data(), w.data(), lnbr.data(), n1, iterations, q.one_minus_omega,
                           history.data(), g_phi.data(), g_src.data(), g_coef.data(), g_w.data());
    at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
      for (int64_t u = u0; u < u1; ++u) {
        const int64_t b = scene[u], slot = u - first[b];
        const T* fs = faces + b * pool * 2;
        for (uint64_t bits = listed[u]; bits; bits &= bits - 1) {
          const int l = lowest_bit(bits);
          const int64_t i = list_index(u, l);
          T mass[6], mom[6], g_inv[6];
          cell_faces(fs, slot, l, nbr.data() + 6 * u, mass, mom);
          for (int d = 0; d < 6; ++d) g_inv[d] = g_w[size_t(d * n1 + i)];
          T* cg = cell_g.data() + 12 * i;
          cell_entry_adjoint(mass, mom, q, g_src[size_t(i)], g_coef[size_t(i)], g_inv, cg, cg + 6);
        }
      }
    });
  }
  // every face of the used slots: the field's adjoint, plus the cells that read it (as the lower
  // c-face of its own cell, as the upper c-face of the cell below along c)
  at::parallel_for(0, U, kSlotGrain, [&](int64_t u0, int64_t u1) {
    for (int64_t u = u0; u < u1; ++u) {
      const int64_t b = scene[u], slot = u - first[b];
      const T* fs = faces + b * pool * 2;
      const T* ps = phi_pool.data() + b * K * kBlockCells;
      const T* gfs = g_field + b * pool;
      T* out = g_faces + b * pool * 2;
      const int32_t* nu = nbr.data() + 6 * u;
      for (int c = 0; c < 3; ++c)
        for (int l = 0; l < kBlockCells; ++l) {
          const int64_t f = (slot * 3 + c) * kBlockCells + l;
          T gm, gp;
          face_field_adjoint(fs, ps, slot, c, l, nu, q, gfs[f], &gm, &gp);
          const int64_t own = list_index(u, l);
          if (own >= 0) {
            gm = gm + cell_g[size_t(12 * own + 2 * c)];
            gp = gp + cell_g[size_t(12 * own + 6 + 2 * c)];
          }
          int64_t lo_slot;
          const int lo = neighbour_cell(l, 2 * c, slot, nu, &lo_slot);
          const int64_t below = lo_slot < 0 ? -1 : list_index(first[b] + lo_slot, lo);
          if (below >= 0) {
            gm = gm + cell_g[size_t(12 * below + 2 * c + 1)];
            gp = gp + cell_g[size_t(12 * below + 6 + 2 * c + 1)];
          }
          out[2 * f] = gm;
          out[2 * f + 1] = gp;
        }
    }
  });
}

at::Tensor pressure_adjoint_cpu(const at::Tensor& faces, const at::Tensor& table, const at::Tensor& blocks,
                                const at::Tensor& count, const at::Tensor& target, const at::Tensor& dt,
                                double cell_size, int64_t resolution, int64_t iterations, double omega,
                                double stiffness, double pic, const at::Tensor& g_field) {
  constexpr const char* op = "pressure_adjoint";
  const int64_t r = resolution;
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cpu::pressure_adjoint: need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(faces.dim() == 5 && faces.size(2) == 3 && faces.size(3) == kBlockCells && faces.size(4) == 2,
              "ams_torch_cpu::pressure_adjoint: faces must be (B, K, 3, 64, 2), got ", faces.sizes());
  const auto dtype = faces.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "ams_torch_cpu::pressure_adjoint: float32 or float64 only");
  const int64_t B = faces.size(0), K = faces.size(1), nb = blocks_per_axis(r);
  check_float(op, faces, "faces", dtype);
  check_table(op, table, "table", {B, nb * nb * nb});
  check_table(op, blocks, "blocks", {B, K});
  check_table(op, count, "count", {B});
  check_float(op, target, "target", dtype);
  check_float(op, dt, "dt", dtype);
  TORCH_CHECK(target.dim() == 0 && dt.dim() == 0, "ams_torch_cpu::pressure_adjoint: target and dt must be 0-d");
  TORCH_CHECK(iterations >= 0, "ams_torch_cpu::pressure_adjoint: iterations must be >= 0");
  check_float(op, g_field, "g_field", dtype);
  check_shape(op, g_field, "g_field", {B, K, 3, kBlockCells});
  at::Tensor g_faces = at::zeros({B, K, 3, kBlockCells, 2}, faces.options());
  if (B == 0) return g_faces;
  const at::Tensor fc = faces.contiguous(), tc = table.contiguous(), bc = blocks.contiguous(), cc = count.contiguous(),
                   gc = g_field.contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "ams_torch_cpu::pressure_adjoint", [&] {
    pressure_adjoint_impl<scalar_t>(fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(),
                                    bc.const_data_ptr<int32_t>(), cc.const_data_ptr<int32_t>(), target.item<scalar_t>(),
                                    dt.item<scalar_t>(), gc.const_data_ptr<scalar_t>(),
                                    g_faces.mutable_data_ptr<scalar_t>(), B, r, K, cell_size, iterations, omega,
                                    stiffness, pic);
  });
  return g_faces;
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::grid::kP2GAdjointSchema);
  m.def(ams_torch::grid::kG2PAdjointSchema);
  m.def(ams_torch::grid::kPressureAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("p2g_adjoint", &ams_torch::grid::p2g_adjoint_cpu);
  m.impl("g2p_adjoint", &ams_torch::grid::g2p_adjoint_cpu);
  m.impl("pressure_adjoint", &ams_torch::grid::pressure_adjoint_cpu);
}
