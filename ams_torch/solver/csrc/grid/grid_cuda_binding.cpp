// Torch binding of the CUDA hair–hair grid kernels: ops `ams_torch_grid_cuda::{p2g, pressure,
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

#include "grid.h"
#include "grid_cuda.h"

namespace ams_torch {
namespace grid {
namespace {

void check_device(const char* op, const at::Tensor& t, const char* name, const at::Tensor& like) {
  TORCH_CHECK(t.is_cuda() && t.device() == like.device(), "ams_torch_grid_cuda::", op, ": ", name,
              " must be on ", like.device());
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "ams_torch_grid_cuda::", op, ": ", name, " must be ",
              like.scalar_type(), ", got ", t.scalar_type());
}

void check_particles(const char* op, const at::Tensor& x, const at::Tensor& v, const at::Tensor& frame,
                     const at::Tensor& origin, double cell_size, int64_t r) {
  TORCH_CHECK(x.is_cuda(), "ams_torch_grid_cuda::", op, ": x must be a CUDA tensor");
  TORCH_CHECK(x.dim() == 3 && x.size(2) == 3, "ams_torch_grid_cuda::", op, ": x must be (B, P, 3), got ", x.sizes());
  TORCH_CHECK(v.sizes() == x.sizes(), "ams_torch_grid_cuda::", op, ": v must be ", x.sizes(), ", got ", v.sizes());
  TORCH_CHECK(frame.dim() == 3 && frame.size(0) == x.size(0) && frame.size(1) == 6 && frame.size(2) == 3,
              "ams_torch_grid_cuda::", op, ": frame must be (B, 6, 3), got ", frame.sizes());
  TORCH_CHECK(origin.dim() == 1 && origin.size(0) == 3, "ams_torch_grid_cuda::", op, ": origin must be (3,)");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_grid_cuda::", op, ": need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, "ams_torch_grid_cuda::", op,
              ": float32 or float64 only");
  check_device(op, v, "v", x);
  check_device(op, frame, "frame", x);
  check_device(op, origin, "origin", x);
}

void check_launch(const char* op, cudaError_t err) {
  TORCH_CHECK(err == cudaSuccess, "ams_torch_grid_cuda::", op, ": kernel launch failed: ", cudaGetErrorString(err));
}

at::Tensor p2g_cuda_op(const at::Tensor& x, const at::Tensor& v, const at::Tensor& m, const at::Tensor& frame,
                       const at::Tensor& origin, double cell_size, int64_t resolution) {
  check_particles("p2g", x, v, frame, origin, cell_size, resolution);
  TORCH_CHECK(m.dim() == 2 && m.size(0) == x.size(0) && m.size(1) == x.size(1),
              "ams_torch_grid_cuda::p2g: m must be (B, P), got ", m.sizes());
  check_device("p2g", m, "m", x);
  // float atomics: the summation order (the last bits of the faces) varies between runs. The registered
  // op ams_torch::hair_hair_p2g takes the torch definition under torch.use_deterministic_algorithms(True).
  at::globalContext().alertNotDeterministic("ams_torch_grid_cuda::p2g");
  const c10::cuda::CUDAGuard guard(x.device());
  const int64_t B = x.size(0), P = x.size(1), r = resolution;
  at::Tensor faces = at::empty({B, 3, num_faces(r), 2}, x.options());
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), mc = m.contiguous(), fc = frame.contiguous(),
                   oc = origin.contiguous();
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_grid_cuda::p2g", [&] {
    err = p2g_cuda<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                             mc.const_data_ptr<scalar_t>(), fc.const_data_ptr<scalar_t>(),
                             oc.const_data_ptr<scalar_t>(), faces.mutable_data_ptr<scalar_t>(), B, P, r, cell_size,
                             stream);
  });
  check_launch("p2g", err);
  return faces;
}

std::tuple<at::Tensor, at::Tensor> pressure_cuda_op(const at::Tensor& faces, const at::Tensor& target,
                                                    const at::Tensor& dt, double cell_size, int64_t resolution,
                                                    int64_t iterations, double omega, double stiffness, double pic) {
  const int64_t r = resolution;
  TORCH_CHECK(faces.is_cuda(), "ams_torch_grid_cuda::pressure: faces must be a CUDA tensor");
  TORCH_CHECK(r >= 2 && cell_size > 0, "ams_torch_grid_cuda::pressure: need resolution >= 2 and cell_size > 0");
  TORCH_CHECK(faces.dim() == 4 && faces.size(1) == 3 && faces.size(2) == num_faces(r) && faces.size(3) == 2,
              "ams_torch_grid_cuda::pressure: faces must be (B, 3, (R+1) R R, 2), got ", faces.sizes());
  TORCH_CHECK(faces.scalar_type() == at::kFloat || faces.scalar_type() == at::kDouble,
              "ams_torch_grid_cuda::pressure: float32 or float64 only");
  TORCH_CHECK(target.dim() == 0 && dt.dim() == 0, "ams_torch_grid_cuda::pressure: target and dt must be 0-d tensors");
  TORCH_CHECK(iterations >= 0, "ams_torch_grid_cuda::pressure: iterations must be >= 0");
  check_device("pressure", target, "target", faces);
  check_device("pressure", dt, "dt", faces);
  const c10::cuda::CUDAGuard guard(faces.device());
  const int64_t B = faces.size(0), r3 = r * r * r;
  at::Tensor phi_a = at::empty({B, r, r, r}, faces.options());
  at::Tensor phi_b = iterations > 0 ? at::empty({B, r, r, r}, faces.options()) : phi_a;
  at::Tensor field = at::empty({B, 3, num_faces(r)}, faces.options());
  const int64_t listed = iterations > 0 ? B * r3 : 0; // static capacity: every cell of every scene
  at::Tensor entries = at::empty({listed * kEntry}, faces.options());
  at::Tensor cells = at::empty({listed}, faces.options().dtype(at::kInt));
  at::Tensor counters = at::empty({2 * B}, faces.options().dtype(at::kInt));
  const at::Tensor fc = faces.contiguous();
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(faces.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(faces.scalar_type(), "ams_torch_grid_cuda::pressure", [&] {
    err = pressure_cuda<scalar_t>(fc.const_data_ptr<scalar_t>(), target.const_data_ptr<scalar_t>(),
                                  dt.const_data_ptr<scalar_t>(), phi_a.mutable_data_ptr<scalar_t>(),
                                  phi_b.mutable_data_ptr<scalar_t>(), field.mutable_data_ptr<scalar_t>(),
                                  entries.mutable_data_ptr<scalar_t>(), cells.mutable_data_ptr<int32_t>(),
                                  counters.mutable_data_ptr<int32_t>(), B, r, cell_size, iterations, omega, stiffness,
                                  pic, stream);
  });
  check_launch("pressure", err);
  return {iterations % 2 == 0 ? phi_a : phi_b, field};
}

std::tuple<at::Tensor, at::Tensor> g2p_cuda_op(const at::Tensor& x, const at::Tensor& v, const at::Tensor& field,
                                               const at::Tensor& frame, const at::Tensor& origin,
                                               const at::Tensor& free, const at::Tensor& dt, double cell_size,
                                               int64_t resolution, double pic) {
  check_particles("g2p", x, v, frame, origin, cell_size, resolution);
  const int64_t B = x.size(0), P = x.size(1), r = resolution;
  TORCH_CHECK(field.dim() == 3 && field.size(0) == B && field.size(1) == 3 && field.size(2) == num_faces(r),
              "ams_torch_grid_cuda::g2p: field must be (B, 3, (R+1) R R), got ", field.sizes());
  check_device("g2p", field, "field", x);
  check_device("g2p", dt, "dt", x);
  TORCH_CHECK(dt.dim() == 0, "ams_torch_grid_cuda::g2p: dt must be a 0-d tensor");
  TORCH_CHECK(free.dim() == 1 && free.size(0) > 0 && P % free.size(0) == 0 && free.scalar_type() == at::kBool &&
                  free.is_cuda() && free.device() == x.device(),
              "ams_torch_grid_cuda::g2p: free must be a bool tensor (N,) on ", x.device(), " with N dividing P");
  const c10::cuda::CUDAGuard guard(x.device());
  at::Tensor xo = at::empty({B, P, 3}, x.options());
  at::Tensor vo = at::empty({B, P, 3}, x.options());
  const at::Tensor xc = x.contiguous(), vc = v.contiguous(), fc = field.contiguous(), frc = frame.contiguous(),
                   oc = origin.contiguous(), freec = free.contiguous();
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(x.device().index()).stream();
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ams_torch_grid_cuda::g2p", [&] {
    err = g2p_cuda<scalar_t>(xc.const_data_ptr<scalar_t>(), vc.const_data_ptr<scalar_t>(),
                             fc.const_data_ptr<scalar_t>(), frc.const_data_ptr<scalar_t>(),
                             oc.const_data_ptr<scalar_t>(), freec.const_data_ptr<bool>(), free.size(0),
                             dt.const_data_ptr<scalar_t>(), xo.mutable_data_ptr<scalar_t>(),
                             vo.mutable_data_ptr<scalar_t>(), B, P, r, cell_size, pic, stream);
  });
  check_launch("g2p", err);
  return {xo, vo};
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY(ams_torch_grid_cuda, m) {
  m.def("p2g(Tensor x, Tensor v, Tensor m, Tensor frame, Tensor origin, float cell_size, int resolution) -> Tensor");
  m.def("pressure(Tensor faces, Tensor target, Tensor dt, float cell_size, int resolution, int iterations, "
        "float omega, float stiffness, float pic) -> (Tensor, Tensor)");
  m.def("g2p(Tensor x, Tensor v, Tensor field, Tensor frame, Tensor origin, Tensor free, Tensor dt, float cell_size, "
        "int resolution, float pic) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(ams_torch_grid_cuda, CUDA, m) {
  m.impl("p2g", &ams_torch::grid::p2g_cuda_op);
  m.impl("pressure", &ams_torch::grid::pressure_cuda_op);
  m.impl("g2p", &ams_torch::grid::g2p_cuda_op);
}
