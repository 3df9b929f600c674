// CPU kernels of the hair–hair grid: ops `ams_torch_grid_cpu::{p2g, pressure, g2p}` (shapes in
// grid.h and ams_torch/stages/hair_hair/native.py). The arithmetic is grid.h's, shared with CUDA.
//
// Parallelism (at::parallel_for), chosen so that results do not depend on the thread count:
//   * P2G: the particles of each scene are bucketed by x-slab of kSlab cells (stable counting
//     sort on their cell index). A particle of slab s writes only face planes [s kSlab - 1,
//     (s + 1) kSlab] along x, so slabs s and s + 2 never share a face: even slabs are scattered
//     in parallel, then odd slabs. Each face therefore sums its contributions in one fixed order
//     (slab colour, then particle index), whatever the number of threads. (Per-thread grids
//     would cost a full grid of zeroing and reduction per thread, atomics a varying order.)
//   * pressure: active cells (six massive faces) of scenes where some cell pushes (src > 0) are
//     compacted in cell order by x-slabs (count, prefix, fill), with their neighbour masks; the
//     Jacobi sweeps are double-buffered, parallel over the compacted cells. Scenes without a pushing cell skip
//     the sweeps: phi stays exactly 0, as the torch sweeps leave it.
//   * field (per face) and G2P (per particle): independent, parallel.
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

#include "grid.h"

namespace ams_torch {
namespace grid {
namespace {

constexpr int64_t kSlab = 4;          // cells per x-slab of the P2G colouring (>= 2)
constexpr int64_t kParticleGrain = 1024;
constexpr int64_t kCellGrain = 2048;

void check_common(const char* op, const at::Tensor& t, const char* name, at::ScalarType dtype) {
  TORCH_CHECK(t.device().is_cpu(), "ams_torch_grid_cpu::", op, ": ", name, " must be a CPU tensor");
  TORCH_CHECK(t.scalar_type() == dtype, "ams_torch_grid_cpu::", op, ": ", name, " must be ", dtype, ", got ",
              t.scalar_type());
}

void check_particles(const char* op, const at::Tensor& x, const at::Tensor& v, const at::Tensor& frame,
                     const at::Tensor& origin, double cell_size, int64_t r) {
  TORCH_CHECK(x.dim() == 3 && x.size(2) == 3, "ams_torch_grid_cpu::", op, ": x must be (B, P, 3), got ", x.sizes());
  TORCH_CHECK(v.sizes() == x.sizes(), "ams_torch_grid_cpu::", op, ": v must be ", x.sizes(), ", got ", v.sizes());
  TORCH_CHECK(frame.dim() == 3 && frame.size(0) == x.size(0) && frame.size(1) == 6 && frame.size(2) == 3,
              "ams_torch_grid_cpu::", op, ": frame must be (B, 6, 3), got ", frame.sizes());
  TORCH_CHECK(origin.dim() == 1 && origin.size(0) == 3, "ams_torch_grid_cpu::", op, ": origin must be (3,)");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_grid_cpu::", op, ": need resolution >= 2 and cell_size > 0");
  const auto dtype = x.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "ams_torch_grid_cpu::", op, ": float32 or float64 only");
  check_common(op, x, "x", dtype);
  check_common(op, v, "v", dtype);
  check_common(op, frame, "frame", dtype);
  check_common(op, origin, "origin", dtype);
}

template <class T>
void p2g_impl(const T* x, const T* v, const T* m, const T* frame, const T* origin, T* faces, int64_t B, int64_t P,
              int64_t r, double cell_size) {
  const T h = T(cell_size);
  const int64_t nf = num_faces(r);
  const int64_t slabs = (r + kSlab - 1) / kSlab;
  std::vector<T> head(size_t(B * P * 6));
  std::vector<int32_t> slab(size_t(B * P));
  at::parallel_for(0, B * P, kParticleGrain, [&](int64_t begin, int64_t end) {
    for (int64_t q = begin; q < end; ++q) {
      T* xl = head.data() + 6 * q;
      to_head(frame + 18 * (q / P), x + 3 * q, v + 3 * q, xl, xl + 3);
      T cx = grid_floor(cell_coord(xl, origin, h, 0));
      if (!(cx >= T(0))) cx = T(0); // also NaN
      if (cx > T(r - 1)) cx = T(r - 1);
      slab[q] = int32_t(int64_t(cx) / kSlab);
    }
  });
  // stable counting sort of each scene's particles by slab
  std::vector<int64_t> start(size_t(B * (slabs + 1)));
  std::vector<int32_t> order(size_t(B * P));
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      int64_t* st = start.data() + b * (slabs + 1);
      std::fill(st, st + slabs + 1, 0);
      for (int64_t p = 0; p < P; ++p) ++st[slab[b * P + p] + 1];
      for (int64_t s = 0; s < slabs; ++s) st[s + 1] += st[s];
      std::vector<int64_t> fill(st, st + slabs);
      for (int64_t p = 0; p < P; ++p) order[b * P + fill[slab[b * P + p]]++] = int32_t(p);
    }
  });
  const auto add = [](T* ptr, T value) { *ptr += value; };
  for (int64_t colour = 0; colour < 2; ++colour) {
    const int64_t per_scene = (slabs - colour + 1) / 2; // slabs colour, colour + 2, ...
    at::parallel_for(0, B * per_scene, 1, [&](int64_t t0, int64_t t1) {
      for (int64_t t = t0; t < t1; ++t) {
        const int64_t b = t / per_scene;
        const int64_t s = colour + 2 * (t % per_scene);
        const int64_t* st = start.data() + b * (slabs + 1);
        T* fs = faces + b * 3 * nf * 2;
        for (int64_t i = st[s]; i < st[s + 1]; ++i) {
          const int64_t q = b * P + order[b * P + i];
          const T* xl = head.data() + 6 * q;
          p2g_scatter(xl, xl + 3, m[q], origin, h, r, fs, add);
        }
      }
    });
  }
}

at::Tensor p2g_cpu(const at::Tensor& x, const at::Tensor& v, const at::Tensor& m, const at::Tensor& frame,
                   const at::Tensor& origin, double cell_size, int64_t resolution) {
  check_particles("p2g", x, v, frame, origin, cell_size, resolution);
  TORCH_CHECK(m.dim() == 2 && m.size(0) == x.size(0) && m.size(1) == x.size(1),
              "ams_torch_grid_cpu::p2g: m must be (B, P), got ", m.sizes());
  check_common("p2g", m, "m", x.scalar_type());
  const int64_t B = x.size(0), P = x.size(1), r = resolution;
  TORCH_CHECK(P < (int64_t(1) << 31), "ams_torch_grid_cpu::p2g: at most 2^31 - 1 particles per scene");
  at::Tensor faces = at::zeros({B, 3, num_faces(r), 2}, x.options());
  if (B * P == 0) return faces;
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), mc = m.contiguous(), fc = frame.contiguous(),
                   oc = origin.contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_grid_cpu::p2g", [&] {
    p2g_impl<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(), mc.const_data_ptr<scalar_t>(),
                       fc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(), faces.mutable_data_ptr<scalar_t>(),
                       B, P, r, cell_size);
  });
  return faces;
}

template <class T>
void pressure_impl(const T* faces, T rho0, T dt, T* phi_a, T* phi_b, T* field, int64_t B, int64_t r, double cell_size,
                   int64_t iterations, double omega, double stiffness, double pic) {
  const PressureConsts<T> q = pressure_consts<T>(cell_size, rho0, dt, omega, stiffness, pic);
  const int64_t nf = num_faces(r), r3 = r * r * r;
  T* phi = phi_a;
  if (iterations > 0) {
    // pass 1: per (scene, x-slab) the active cells and whether one pushes
    std::vector<int64_t> count(size_t(B * r + 1), 0);
    std::vector<uint8_t> pushes(size_t(B * r), 0);
    at::parallel_for(0, B * r, 1, [&](int64_t s0, int64_t s1) {
      T entry[kEntry];
      for (int64_t s = s0; s < s1; ++s) {
        const T* fs = faces + (s / r) * 3 * nf * 2;
        const int64_t i = s % r;
        for (int64_t j = 0; j < r; ++j)
          for (int64_t k = 0; k < r; ++k)
            if (cell_active(fs, r, i, j, k, q.eps)) {
              ++count[s + 1];
              if (cell_entry(fs, r, i, j, k, q, entry) > T(0)) pushes[s] = 1;
            }
      }
    });
    std::vector<uint8_t> scene_pushes(size_t(B), 0);
    for (int64_t s = 0; s < B * r; ++s) scene_pushes[s / r] |= pushes[s];
    for (int64_t s = 0; s < B * r; ++s) count[s + 1] = count[s] + (scene_pushes[s / r] ? count[s + 1] : 0);
    const int64_t total = count[B * r];
    if (total > 0) {
      // pass 2: the compacted list, in cell order
      std::vector<int64_t> cells(static_cast<size_t>(total));
      std::vector<uint8_t> masks(static_cast<size_t>(total));
      std::vector<T> entries(size_t(total * kEntry));
      at::parallel_for(0, B * r, 1, [&](int64_t s0, int64_t s1) {
        for (int64_t s = s0; s < s1; ++s) {
          if (!scene_pushes[s / r]) continue;
          const T* fs = faces + (s / r) * 3 * nf * 2;
          const int64_t i = s % r;
          int64_t slot = count[s];
          for (int64_t j = 0; j < r; ++j)
            for (int64_t k = 0; k < r; ++k)
              if (cell_active(fs, r, i, j, k, q.eps)) {
                cell_entry(fs, r, i, j, k, q, entries.data() + kEntry * slot);
                masks[slot] = uint8_t(neighbour_mask(r, i, j, k));
                cells[slot++] = (s / r) * r3 + (i * r + j) * r + k;
              }
        }
      });
      for (int64_t it = 0; it < iterations; ++it) {
        const T* src = it % 2 == 0 ? phi_a : phi_b;
        T* dst = it % 2 == 0 ? phi_b : phi_a;
        at::parallel_for(0, total, kCellGrain, [&](int64_t c0, int64_t c1) {
          for (int64_t c = c0; c < c1; ++c) {
            dst[cells[c]] = sweep_cell(src, r, cells[c], masks[c], entries.data() + kEntry * c, q.one_minus_omega);
          }
        });
      }
    }
    phi = iterations % 2 == 0 ? phi_a : phi_b;
  }
  // planes (scene, component, a0) of the face grids, each n1 n2 contiguous faces
  at::parallel_for(0, B * 3 * (r + 1), 1, [&](int64_t w0, int64_t w1) {
    for (int64_t w = w0; w < w1; ++w) {
      const int64_t b = w / (3 * (r + 1));
      const int c = int((w / (r + 1)) % 3);
      const int64_t a0 = w % (r + 1);
      if (c != 0 && a0 == r) continue; // only the x-faces have R + 1 planes along x
      const int64_t n1 = c == 1 ? r + 1 : r, n2 = c == 2 ? r + 1 : r;
      const T* fs = faces + b * 3 * nf * 2;
      const T* ps = phi + b * r3;
      T* out = field + (b * 3 + c) * nf;
      for (int64_t a1 = 0; a1 < n1; ++a1) {
        const int64_t row = (a0 * n1 + a1) * n2;
        for (int64_t a2 = 0; a2 < n2; ++a2) out[row + a2] = face_field(fs, ps, r, c, a0, a1, a2, row + a2, q);
      }
    }
  });
}

std::tuple<at::Tensor, at::Tensor> pressure_cpu(const at::Tensor& faces, const at::Tensor& target, const at::Tensor& dt,
                                                double cell_size, int64_t resolution, int64_t iterations, double omega,
                                                double stiffness, double pic) {
  const int64_t r = resolution;
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_grid_cpu::pressure: need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(faces.dim() == 4 && faces.size(1) == 3 && faces.size(2) == num_faces(r) && faces.size(3) == 2,
              "ams_torch_grid_cpu::pressure: faces must be (B, 3, (R+1) R R, 2), got ", faces.sizes());
  TORCH_CHECK(target.dim() == 0 && dt.dim() == 0, "ams_torch_grid_cpu::pressure: target and dt must be 0-d tensors");
  TORCH_CHECK(iterations >= 0, "ams_torch_grid_cpu::pressure: iterations must be >= 0");
  const auto dtype = faces.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "ams_torch_grid_cpu::pressure: float32 or float64 only");
  check_common("pressure", faces, "faces", dtype);
  check_common("pressure", target, "target", dtype);
  check_common("pressure", dt, "dt", dtype);
  const int64_t B = faces.size(0);
  at::Tensor phi_a = at::zeros({B, r, r, r}, faces.options());
  at::Tensor phi_b = iterations > 0 ? at::zeros({B, r, r, r}, faces.options()) : phi_a;
  at::Tensor field = at::empty({B, 3, num_faces(r)}, faces.options());
  if (B == 0) return {phi_a, field};
  const at::Tensor fc = faces.contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "ams_torch_grid_cpu::pressure", [&] {
    pressure_impl<scalar_t>(fc.const_data_ptr<scalar_t>(), target.item<scalar_t>(), dt.item<scalar_t>(),
                            phi_a.mutable_data_ptr<scalar_t>(), phi_b.mutable_data_ptr<scalar_t>(),
                            field.mutable_data_ptr<scalar_t>(), B, r, cell_size, iterations, omega, stiffness, pic);
  });
  return {iterations % 2 == 0 ? phi_a : phi_b, field};
}

template <class T>
void g2p_impl(const T* x, const T* v, const T* field, const T* frame, const T* origin, const bool* free, T dt, T* xo,
              T* vo, int64_t B, int64_t P, int64_t N, int64_t r, double cell_size, double pic) {
  const T h = T(cell_size), pict = T(pic);
  const int64_t nf = num_faces(r);
  at::parallel_for(0, B * P, kParticleGrain, [&](int64_t begin, int64_t end) {
    for (int64_t q = begin; q < end; ++q) {
      const int64_t b = q / P;
      g2p_particle(frame + 18 * b, x + 3 * q, v + 3 * q, field + b * 3 * nf, origin, h, r, pict, free[(q % P) % N], dt,
                   xo + 3 * q, vo + 3 * q);
    }
  });
}

std::tuple<at::Tensor, at::Tensor> g2p_cpu(const at::Tensor& x, const at::Tensor& v, const at::Tensor& field,
                                           const at::Tensor& frame, const at::Tensor& origin, const at::Tensor& free,
                                           const at::Tensor& dt, double cell_size, int64_t resolution, double pic) {
  check_particles("g2p", x, v, frame, origin, cell_size, resolution);
  const int64_t B = x.size(0), P = x.size(1), r = resolution;
  TORCH_CHECK(field.dim() == 3 && field.size(0) == B && field.size(1) == 3 && field.size(2) == num_faces(r),
              "ams_torch_grid_cpu::g2p: field must be (B, 3, (R+1) R R), got ", field.sizes());
  check_common("g2p", field, "field", x.scalar_type());
  check_common("g2p", dt, "dt", x.scalar_type());
  TORCH_CHECK(dt.dim() == 0, "ams_torch_grid_cpu::g2p: dt must be a 0-d tensor");
  TORCH_CHECK(free.dim() == 1 && free.size(0) > 0 && P % free.size(0) == 0 && free.scalar_type() == at::kBool &&
                  free.device().is_cpu(),
              "ams_torch_grid_cpu::g2p: free must be a CPU bool tensor (N,) with N dividing P, got ", free.sizes());
  at::Tensor xo = at::empty({B, P, 3}, x.options());
  at::Tensor vo = at::empty({B, P, 3}, x.options());
  if (B * P == 0) return {xo, vo};
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), fc = field.contiguous(), frc = frame.contiguous(),
                   oc = origin.contiguous(), freec = free.contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_grid_cpu::g2p", [&] {
    g2p_impl<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(), fc.const_data_ptr<scalar_t>(),
                       frc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(), freec.const_data_ptr<bool>(),
                       dt.item<scalar_t>(), xo.mutable_data_ptr<scalar_t>(), vo.mutable_data_ptr<scalar_t>(), B, P,
                       free.size(0), r, cell_size, pic);
  });
  return {xo, vo};
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY(ams_torch_grid_cpu, m) {
  m.def("p2g(Tensor x, Tensor v, Tensor m, Tensor frame, Tensor origin, float cell_size, int resolution) -> Tensor");
  m.def("pressure(Tensor faces, Tensor target, Tensor dt, float cell_size, int resolution, int iterations, "
        "float omega, float stiffness, float pic) -> (Tensor, Tensor)");
  m.def("g2p(Tensor x, Tensor v, Tensor field, Tensor frame, Tensor origin, Tensor free, Tensor dt, float cell_size, "
        "int resolution, float pic) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(ams_torch_grid_cpu, CPU, m) {
  m.impl("p2g", &ams_torch::grid::p2g_cpu);
  m.impl("pressure", &ams_torch::grid::pressure_cpu);
  m.impl("g2p", &ams_torch::grid::g2p_cpu);
}
