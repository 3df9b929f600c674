// Torch binding of the CUDA adjoints of the hair–hair grid: ops `ams_torch_cuda::{p2g_adjoint,
// pressure_adjoint, g2p_adjoint}`, with the schemas and shapes of the CPU ops (grid_adjoint_cpu.cpp).
// Built only against a CUDA torch; the kernels are in grid_adjoint_cuda.cu. Current CUDA stream of the
// inputs' device, outputs and workspace from torch's caching allocator, no host synchronisation.
#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <tuple>

#include "grid/grid.h"
#include "grid/grid_adjoint_binding.h"
#include "grid/grid_adjoint_cuda.h"

namespace ams_torch {
namespace grid {
namespace {

void check_like(const char* op, const at::Tensor& t, const char* name, const at::Tensor& like) {
  TORCH_CHECK(t.is_cuda() && t.device() == like.device() && t.scalar_type() == like.scalar_type(),
              "ams_torch_cuda::", op, ": ", name, " must be a ", like.scalar_type(), " tensor on ", like.device(),
              ", got ", t.scalar_type(), " on ", t.device());
}

void check_sizes(const char* op, const at::Tensor& t, const char* name, at::IntArrayRef sizes) {
  TORCH_CHECK(t.sizes() == sizes, "ams_torch_cuda::", op, ": ", name, " must be ", sizes, ", got ", t.sizes());
}

void check_ints(const char* op, const at::Tensor& t, const char* name, at::IntArrayRef sizes, const at::Tensor& like) {
  TORCH_CHECK(t.is_cuda() && t.device() == like.device() && t.scalar_type() == at::kInt && t.sizes() == sizes,
              "ams_torch_cuda::", op, ": ", name, " must be an int32 tensor on ", like.device(), " of shape ", sizes,
              ", got ", t.scalar_type(), " ", t.sizes());
}

void check_launch(const char* op, cudaError_t err) {
  TORCH_CHECK(err == cudaSuccess, "ams_torch_cuda::", op, ": kernel launch failed: ", cudaGetErrorString(err));
}

cudaStream_t stream_of(const at::Tensor& t) { return c10::cuda::getCurrentCUDAStream(t.device().index()).stream(); }

// (B, P, nb) after the checks shared by the particle adjoints
std::tuple<int64_t, int64_t, int64_t> particle_args(const char* op, const at::Tensor& xl, const at::Tensor& vl,
                                                    const at::Tensor& origin, const at::Tensor& table, double h,
                                                    int64_t r) {
  TORCH_CHECK(xl.is_cuda() && xl.dim() == 3 && xl.size(2) == 3, "ams_torch_cuda::", op,
              ": xl must be a CUDA tensor (B, P, 3), got ", xl.sizes());
  TORCH_CHECK(xl.scalar_type() == at::kFloat || xl.scalar_type() == at::kDouble, "ams_torch_cuda::", op,
              ": float32 or float64 only");
  TORCH_CHECK(r >= 2 && h > 0, "ams_torch_cuda::", op, ": need resolution >= 2 and cell_size > 0");
  check_like(op, vl, "vl", xl);
  check_sizes(op, vl, "vl", xl.sizes());
  check_like(op, origin, "origin", xl);
  check_sizes(op, origin, "origin", {3});
  const int64_t B = xl.size(0), P = xl.size(1), nb = blocks_per_axis(r);
  check_ints(op, table, "table", {B, nb * nb * nb}, xl);
  return {B, P, nb};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> p2g_adjoint_cuda_op(const at::Tensor& xl, const at::Tensor& vl,
                                                                   const at::Tensor& m, const at::Tensor& origin,
                                                                   const at::Tensor& table, const at::Tensor& g_faces,
                                                                   double cell_size, int64_t resolution) {
  constexpr const char* op = "p2g_adjoint";
  const auto [B, P, nb] = particle_args(op, xl, vl, origin, table, cell_size, resolution);
  check_like(op, m, "m", xl);
  check_sizes(op, m, "m", {B, P});
  check_like(op, g_faces, "g_faces", xl);
  TORCH_CHECK(g_faces.dim() == 5 && g_faces.size(0) == B && g_faces.size(2) == 3 && g_faces.size(3) == kBlockCells &&
                  g_faces.size(4) == 2,
              "ams_torch_cuda::p2g_adjoint: g_faces must be (B, K, 3, 64, 2), got ", g_faces.sizes());
  const c10::cuda::CUDAGuard guard(xl.device());
  at::Tensor g_xl = at::empty({B, P, 3}, xl.options()), g_vl = at::empty({B, P, 3}, xl.options());
  at::Tensor g_m = at::empty({B, P}, xl.options());
  const at::Tensor xc = xl.contiguous(), vc = vl.contiguous(), mc = m.contiguous(), oc = origin.contiguous(),
                   tc = table.contiguous(), gc = g_faces.contiguous();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(xl.scalar_type(), "ams_torch_cuda::p2g_adjoint", [&] {
    err = p2g_adjoint_cuda<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                                     mc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(),
                                     tc.const_data_ptr<int32_t>(), gc.const_data_ptr<scalar_t>(),
                                     g_xl.mutable_data_ptr<scalar_t>(), g_vl.mutable_data_ptr<scalar_t>(),
                                     g_m.mutable_data_ptr<scalar_t>(), B, P, resolution, g_faces.size(1), cell_size,
                                     stream_of(xl));
  });
  check_launch(op, err);
  return {g_xl, g_vl, g_m};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> g2p_adjoint_cuda_op(
    const at::Tensor& xl, const at::Tensor& vl, const at::Tensor& field, const at::Tensor& table,
    const at::Tensor& origin, const at::Tensor& g_dv, double cell_size, int64_t resolution, double pic) {
  constexpr const char* op = "g2p_adjoint";
  const auto [B, P, nb] = particle_args(op, xl, vl, origin, table, cell_size, resolution);
  check_like(op, field, "field", xl);
  TORCH_CHECK(field.dim() == 4 && field.size(0) == B && field.size(2) == 3 && field.size(3) == kBlockCells,
              "ams_torch_cuda::g2p_adjoint: field must be (B, K, 3, 64), got ", field.sizes());
  check_like(op, g_dv, "g_dv", xl);
  check_sizes(op, g_dv, "g_dv", xl.sizes());
  at::globalContext().alertNotDeterministic("ams_torch_cuda::g2p_adjoint (float atomicAdd into the field's adjoint)");
  const c10::cuda::CUDAGuard guard(xl.device());
  const int64_t K = field.size(1);
  at::Tensor g_xl = at::empty({B, P, 3}, xl.options()), g_vl = at::empty({B, P, 3}, xl.options());
  at::Tensor g_field = at::empty({B, K, 3, kBlockCells}, xl.options()), dv = at::empty({B, P, 3}, xl.options());
  const at::Tensor xc = xl.contiguous(), vc = vl.contiguous(), fc = field.contiguous(), tc = table.contiguous(),
                   oc = origin.contiguous(), gc = g_dv.contiguous();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(xl.scalar_type(), "ams_torch_cuda::g2p_adjoint", [&] {
    err = g2p_adjoint_cuda<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                                     fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(),
                                     oc.const_data_ptr<scalar_t>(), gc.const_data_ptr<scalar_t>(),
                                     g_xl.mutable_data_ptr<scalar_t>(), g_vl.mutable_data_ptr<scalar_t>(),
                                     g_field.mutable_data_ptr<scalar_t>(), dv.mutable_data_ptr<scalar_t>(), B, P,
                                     resolution, K, cell_size, pic, stream_of(xl));
  });
  check_launch(op, err);
  return {g_xl, g_vl, g_field, dv};
}

at::Tensor pressure_adjoint_cuda_op(const at::Tensor& faces, const at::Tensor& table, const at::Tensor& blocks,
                                    const at::Tensor& count, const at::Tensor& target, const at::Tensor& dt,
                                    double cell_size, int64_t resolution, int64_t iterations, double omega,
                                    double stiffness, double pic, const at::Tensor& g_field) {
  constexpr const char* op = "pressure_adjoint";
  const int64_t r = resolution;
  TORCH_CHECK(faces.is_cuda() && faces.dim() == 5 && faces.size(2) == 3 && faces.size(3) == kBlockCells &&
                  faces.size(4) == 2,
              "ams_torch_cuda::pressure_adjoint: faces must be a CUDA tensor (B, K, 3, 64, 2), got ", faces.sizes());
  TORCH_CHECK(faces.scalar_type() == at::kFloat || faces.scalar_type() == at::kDouble,
              "ams_torch_cuda::pressure_adjoint: float32 or float64 only");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cuda::pressure_adjoint: need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(iterations >= 0, "ams_torch_cuda::pressure_adjoint: iterations must be >= 0");
  const int64_t B = faces.size(0), K = faces.size(1), nb = blocks_per_axis(r);
  check_ints(op, table, "table", {B, nb * nb * nb}, faces);
  check_ints(op, blocks, "blocks", {B, K}, faces);
  check_ints(op, count, "count", {B}, faces);
  check_like(op, target, "target", faces);
  check_like(op, dt, "dt", faces);
  TORCH_CHECK(target.dim() == 0 && dt.dim() == 0, "ams_torch_cuda::pressure_adjoint: target and dt must be 0-d");
  check_like(op, g_field, "g_field", faces);
  check_sizes(op, g_field, "g_field", {B, K, 3, kBlockCells});
  const c10::cuda::CUDAGuard guard(faces.device());
  at::Tensor g_faces = at::empty({B, K, 3, kBlockCells, 2}, faces.options());
  at::Tensor work = at::empty({pressure_adjoint_workspace(B, K, iterations, false)}, faces.options());
  at::Tensor iwork = at::empty({pressure_adjoint_workspace(B, K, iterations, true)}, faces.options().dtype(at::kInt));
  const at::Tensor fc = faces.contiguous(), tc = table.contiguous(), bc = blocks.contiguous(), cc = count.contiguous(),
                   gc = g_field.contiguous();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(faces.scalar_type(), "ams_torch_cuda::pressure_adjoint", [&] {
    err = pressure_adjoint_cuda<scalar_t>(
        fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(), bc.const_data_ptr<int32_t>(),
        cc.const_data_ptr<int32_t>(), target.const_data_ptr<scalar_t>(), dt.const_data_ptr<scalar_t>(),
        gc.const_data_ptr<scalar_t>(), g_faces.mutable_data_ptr<scalar_t>(), work.mutable_data_ptr<scalar_t>(),
        iwork.mutable_data_ptr<int32_t>(), B, r, K, cell_size, iterations, omega, stiffness, pic, stream_of(faces));
  });
  check_launch(op, err);
  return g_faces;
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def(ams_torch::grid::kP2GAdjointSchema);
  m.def(ams_torch::grid::kG2PAdjointSchema);
  m.def(ams_torch::grid::kPressureAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("p2g_adjoint", &ams_torch::grid::p2g_adjoint_cuda_op);
  m.impl("g2p_adjoint", &ams_torch::grid::g2p_adjoint_cuda_op);
  m.impl("pressure_adjoint", &ams_torch::grid::pressure_adjoint_cuda_op);
}
