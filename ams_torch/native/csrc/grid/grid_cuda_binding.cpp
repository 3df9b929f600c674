// Torch binding of the CUDA block-sparse hair–hair grid kernels: ops `ams_torch_cuda::{p2g, pressure,
// g2p}`, with the schemas of the CPU ops (grid_cpu.cpp). Built only against a CUDA torch; the
// kernels are in grid_cuda.cu (nvcc without torch headers). Runs on the current CUDA stream of
// the inputs' device, with outputs and workspace from torch's caching allocator; reads the
// scalars (target density, dt) on the device, so nothing synchronises with the host.
#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <tuple>

#include "grid/grid.h"
#include "grid/grid_cuda.h"

namespace ams_torch {
namespace grid {
namespace {

void check_device(const char* op, const at::Tensor& t, const char* name, const at::Tensor& like) {
  TORCH_CHECK(t.is_cuda() && t.device() == like.device(), "ams_torch_cuda::", op, ": ", name,
              " must be on ", like.device());
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "ams_torch_cuda::", op, ": ", name, " must be ",
              like.scalar_type(), ", got ", t.scalar_type());
}

void check_particles(const char* op, const at::Tensor& x, const at::Tensor& v, const at::Tensor& frame,
                     const at::Tensor& origin, double cell_size, int64_t r) {
  TORCH_CHECK(x.is_cuda(), "ams_torch_cuda::", op, ": x must be a CUDA tensor");
  TORCH_CHECK(x.dim() == 3 && x.size(2) == 3, "ams_torch_cuda::", op, ": x must be (B, P, 3), got ", x.sizes());
  TORCH_CHECK(v.sizes() == x.sizes(), "ams_torch_cuda::", op, ": v must be ", x.sizes(), ", got ", v.sizes());
  TORCH_CHECK(frame.dim() == 3 && frame.size(0) == x.size(0) && frame.size(1) == 6 && frame.size(2) == 3,
              "ams_torch_cuda::", op, ": frame must be (B, 6, 3), got ", frame.sizes());
  TORCH_CHECK(origin.dim() == 1 && origin.size(0) == 3, "ams_torch_cuda::", op, ": origin must be (3,)");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cuda::", op, ": need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, "ams_torch_cuda::", op,
              ": float32 or float64 only");
  check_device(op, v, "v", x);
  check_device(op, frame, "frame", x);
  check_device(op, origin, "origin", x);
}

void check_launch(const char* op, cudaError_t err) {
  TORCH_CHECK(err == cudaSuccess, "ams_torch_cuda::", op, ": kernel launch failed: ", cudaGetErrorString(err));
}

void check_int(const char* op, const at::Tensor& t, const char* name, at::IntArrayRef sizes, const at::Tensor& like) {
  TORCH_CHECK(t.is_cuda() && t.device() == like.device() && t.scalar_type() == at::kInt && t.sizes() == sizes,
              "ams_torch_cuda::", op, ": ", name, " must be an int32 tensor on ", like.device(), " of shape ",
              sizes, ", got ", t.scalar_type(), " ", t.sizes());
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> p2g_cuda_op(const at::Tensor& x, const at::Tensor& v,
                                                                       const at::Tensor& m, const at::Tensor& frame,
                                                                       const at::Tensor& origin, double cell_size,
                                                                       int64_t resolution, int64_t capacity) {
  check_particles("p2g", x, v, frame, origin, cell_size, resolution);
  TORCH_CHECK(m.dim() == 2 && m.size(0) == x.size(0) && m.size(1) == x.size(1),
              "ams_torch_cuda::p2g: m must be (B, P), got ", m.sizes());
  check_device("p2g", m, "m", x);
  // float atomics: the summation order (the last bits of the faces) varies between runs. The registered
  // op ams_torch::hair_hair_p2g takes the torch definition under torch.use_deterministic_algorithms(True).
  at::globalContext().alertNotDeterministic("ams_torch_cuda::p2g");
  const int64_t B = x.size(0), P = x.size(1), r = resolution, K = capacity, nb = blocks_per_axis(r);
  const int64_t nb3 = nb * nb * nb;
  TORCH_CHECK(nb3 < (int64_t(1) << 31), "ams_torch_cuda::p2g: resolution too large (at most 2^31 - 1 blocks)");
  TORCH_CHECK(K >= 1 && K <= nb3, "ams_torch_cuda::p2g: capacity must be in [1, ", nb3, "] blocks, got ", K);
  const c10::cuda::CUDAGuard guard(x.device());
  at::Tensor faces = at::empty({B, K, 3, kBlockCells, 2}, x.options());
  at::Tensor table = at::empty({B, nb3}, x.options().dtype(at::kInt));
  at::Tensor blocks = at::empty({B, K}, x.options().dtype(at::kInt));
  at::Tensor count = at::empty({B}, x.options().dtype(at::kInt));
  at::Tensor mark = at::empty({B * nb3}, x.options().dtype(at::kByte));
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), mc = m.contiguous(), fc = frame.contiguous(),
                   oc = origin.contiguous();
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_cuda::p2g", [&] {
    err = p2g_cuda<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                             mc.const_data_ptr<scalar_t>(), fc.const_data_ptr<scalar_t>(),
                             oc.const_data_ptr<scalar_t>(), faces.mutable_data_ptr<scalar_t>(),
                             table.mutable_data_ptr<int32_t>(), blocks.mutable_data_ptr<int32_t>(),
                             count.mutable_data_ptr<int32_t>(), mark.mutable_data_ptr<uint8_t>(), B, P, r, K,
                             cell_size, stream);
  });
  check_launch("p2g", err);
  return {faces, table, blocks, count};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> pressure_cuda_op(const at::Tensor& faces, const at::Tensor& table,
                                                                const at::Tensor& blocks, const at::Tensor& count,
                                                                const at::Tensor& target, const at::Tensor& dt,
                                                                double cell_size, int64_t resolution,
                                                                int64_t iterations, double omega, double stiffness,
                                                                double pic, int64_t active_capacity) {
  const int64_t r = resolution;
  TORCH_CHECK(faces.is_cuda(), "ams_torch_cuda::pressure: faces must be a CUDA tensor");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_cuda::pressure: need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(faces.dim() == 5 && faces.size(2) == 3 && faces.size(3) == kBlockCells && faces.size(4) == 2,
              "ams_torch_cuda::pressure: faces must be (B, K, 3, 64, 2), got ", faces.sizes());
  TORCH_CHECK(faces.scalar_type() == at::kFloat || faces.scalar_type() == at::kDouble,
              "ams_torch_cuda::pressure: float32 or float64 only");
  TORCH_CHECK(target.dim() == 0 && dt.dim() == 0, "ams_torch_cuda::pressure: target and dt must be 0-d tensors");
  TORCH_CHECK(iterations >= 0, "ams_torch_cuda::pressure: iterations must be >= 0");
  const int64_t B = faces.size(0), K = faces.size(1), nb = blocks_per_axis(r);
  check_int("pressure", table, "table", {B, nb * nb * nb}, faces);
  check_int("pressure", blocks, "blocks", {B, K}, faces);
  check_int("pressure", count, "count", {B}, faces);
  check_device("pressure", target, "target", faces);
  check_device("pressure", dt, "dt", faces);
  const c10::cuda::CUDAGuard guard(faces.device());
  at::Tensor phi_a = at::empty({B, K, kBlockCells}, faces.options());
  at::Tensor phi_b = at::empty({B, K, kBlockCells}, faces.options());
  at::Tensor field = at::empty({B, K, 3, kBlockCells}, faces.options());
  at::Tensor entries = at::empty({iterations > 0 ? B * K * kBlockCells * kEntry : 0}, faces.options());
  at::Tensor nbr = at::empty({B * K * 6}, faces.options().dtype(at::kInt));
  at::Tensor pushes = at::empty({B}, faces.options().dtype(at::kInt));
  at::Tensor active = at::empty({B}, faces.options().dtype(at::kInt));
  at::Tensor overflow = at::empty({B}, faces.options().dtype(at::kBool));
  const at::Tensor fc = faces.contiguous(), tc = table.contiguous(), bc = blocks.contiguous(), cc = count.contiguous();
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(faces.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(faces.scalar_type(), "ams_torch_cuda::pressure", [&] {
    err = pressure_cuda<scalar_t>(fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(),
                                  bc.const_data_ptr<int32_t>(), cc.const_data_ptr<int32_t>(),
                                  target.const_data_ptr<scalar_t>(), dt.const_data_ptr<scalar_t>(),
                                  phi_a.mutable_data_ptr<scalar_t>(), phi_b.mutable_data_ptr<scalar_t>(),
                                  field.mutable_data_ptr<scalar_t>(), overflow.mutable_data_ptr<bool>(),
                                  entries.mutable_data_ptr<scalar_t>(),
                                  nbr.mutable_data_ptr<int32_t>(), pushes.mutable_data_ptr<int32_t>(),
                                  active.mutable_data_ptr<int32_t>(), B, r, K, cell_size, iterations, omega, stiffness,
                                  pic, active_capacity, stream);
  });
  check_launch("pressure", err);
  return {iterations % 2 == 0 ? phi_a : phi_b, field, overflow};
}

std::tuple<at::Tensor, at::Tensor> g2p_cuda_op(const at::Tensor& x, const at::Tensor& v, const at::Tensor& field,
                                               const at::Tensor& table, const at::Tensor& frame,
                                               const at::Tensor& origin, const at::Tensor& free, const at::Tensor& dt,
                                               double cell_size, int64_t resolution, double pic) {
  check_particles("g2p", x, v, frame, origin, cell_size, resolution);
  const int64_t B = x.size(0), P = x.size(1), r = resolution, nb = blocks_per_axis(r);
  TORCH_CHECK(field.dim() == 4 && field.size(0) == B && field.size(2) == 3 && field.size(3) == kBlockCells,
              "ams_torch_cuda::g2p: field must be (B, K, 3, 64), got ", field.sizes());
  const int64_t K = field.size(1);
  check_device("g2p", field, "field", x);
  check_int("g2p", table, "table", {B, nb * nb * nb}, x);
  check_device("g2p", dt, "dt", x);
  TORCH_CHECK(dt.dim() == 0, "ams_torch_cuda::g2p: dt must be a 0-d tensor");
  TORCH_CHECK(free.dim() == 1 && free.size(0) > 0 && P % free.size(0) == 0 && free.scalar_type() == at::kBool &&
                  free.is_cuda() && free.device() == x.device(),
              "ams_torch_cuda::g2p: free must be a bool tensor (N,) on ", x.device(), " with N dividing P");
  const c10::cuda::CUDAGuard guard(x.device());
  at::Tensor xo = at::empty({B, P, 3}, x.options());
  at::Tensor vo = at::empty({B, P, 3}, x.options());
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), fc = field.contiguous(), tc = table.contiguous(),
                   frc = frame.contiguous(), oc = origin.contiguous(), freec = free.contiguous();
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_cuda::g2p", [&] {
    err = g2p_cuda<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                             fc.const_data_ptr<scalar_t>(), tc.const_data_ptr<int32_t>(),
                             frc.const_data_ptr<scalar_t>(), oc.const_data_ptr<scalar_t>(),
                             freec.const_data_ptr<bool>(), free.size(0), dt.const_data_ptr<scalar_t>(),
                             xo.mutable_data_ptr<scalar_t>(), vo.mutable_data_ptr<scalar_t>(), B, P, r, K, cell_size,
                             pic, stream);
  });
  check_launch("g2p", err);
  return {xo, vo};
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cuda, m) {
  m.def("p2g(Tensor x, Tensor v, Tensor m, Tensor frame, Tensor origin, float cell_size, int resolution, "
        "int capacity) -> (Tensor, Tensor, Tensor, Tensor)");
  m.def("pressure(Tensor faces, Tensor table, Tensor blocks, Tensor count, Tensor target, Tensor dt, "
        "float cell_size, int resolution, int iterations, float omega, float stiffness, float pic, int active_capacity) "
        "-> (Tensor, Tensor, Tensor)");
  m.def("g2p(Tensor x, Tensor v, Tensor field, Tensor table, Tensor frame, Tensor origin, Tensor free, Tensor dt, "
        "float cell_size, int resolution, float pic) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(ams_torch_cuda, CUDA, m) {
  m.impl("p2g", &ams_torch::grid::p2g_cuda_op);
  m.impl("pressure", &ams_torch::grid::pressure_cuda_op);
  m.impl("g2p", &ams_torch::grid::g2p_cuda_op);
}
