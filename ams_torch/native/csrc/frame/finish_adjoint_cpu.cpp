// CPU kernels of the finish and yield adjoints: ops `ams_torch_cpu::finish_adjoint` and
// `yield_adjoint` (schemas in finish_adjoint_binding.h, arithmetic in finish_adjoint.h). Strands
// (finish) or particles (yield) in parallel; the pose adjoints per strand (summed by the caller,
// so the sums do not depend on the thread count).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <optional>
#include <tuple>

#include "frame/finish_adjoint.h"
#include "frame/finish_adjoint_binding.h"

namespace ams_torch {
namespace frame {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> finish_adjoint_cpu(const at::Tensor& x, const at::Tensor& v,
                                                                  const at::Tensor& num_pinned, at::TensorList pose,
                                                                  const at::Tensor& g_v,
                                                                  const std::optional<at::Tensor>& g_speed) {
  constexpr const char* op = "ams_torch_cpu::finish_adjoint";
  const FinishAdjointInputs fa = check_finish_adjoint_inputs(op, x, v, num_pinned, pose, g_v, g_speed);
  const FinishInputs& in = fa.in;
  TORCH_CHECK(in.x.device().is_cpu(), op, ": CPU tensors expected");
  const int64_t strands = in.scenes * in.strands, n = in.particles;
  at::Tensor gx = at::empty(x.sizes(), in.x.options()), gv = at::empty(x.sizes(), in.x.options());
  at::Tensor gp = at::empty({strands, 9}, in.x.options());
  if (strands > 0 && n > 0) {
    AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
      const FinishArgs<scalar_t> a = finish_args<scalar_t>(in);
      const scalar_t* gs = fa.g_speed.defined() ? fa.g_speed.const_data_ptr<scalar_t>() : nullptr;
      at::parallel_for(0, strands, std::max<int64_t>(1, 4096 / n), [&](int64_t begin, int64_t end) {
        for (int64_t g = begin; g < end; ++g)
          finish_adjoint_strand(a, g, fa.g_v.const_data_ptr<scalar_t>(), gs, gx.mutable_data_ptr<scalar_t>(),
                                gv.mutable_data_ptr<scalar_t>(), gp.mutable_data_ptr<scalar_t>());
      });
    });
  }
  return {gx, gv, gp};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> yield_adjoint_cpu(const at::Tensor& x, const at::Tensor& anchor,
                                                                 const at::Tensor& limit, const at::Tensor& free,
                                                                 const at::Tensor& g_new) {
  constexpr const char* op = "ams_torch_cpu::yield_adjoint";
  const YieldInputs in = check_yield_inputs(op, x, anchor, limit, free, g_new);
  TORCH_CHECK(in.x.device().is_cpu(), op, ": CPU tensors expected");
  at::Tensor gx = at::empty(x.sizes(), in.x.options()), ga = at::empty(x.sizes(), in.x.options());
  at::Tensor gl = at::empty(x.sizes().slice(0, x.dim() - 1), in.x.options());
  const int64_t per_scene = in.strands * in.particles;
  AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
    const scalar_t *xp = in.x.const_data_ptr<scalar_t>(), *ap = in.anchor.const_data_ptr<scalar_t>(),
                   *lp = in.limit.const_data_ptr<scalar_t>(), *gp = in.g_new.const_data_ptr<scalar_t>();
    const bool* fp = in.free.const_data_ptr<bool>();
    scalar_t *gxp = gx.mutable_data_ptr<scalar_t>(), *gap = ga.mutable_data_ptr<scalar_t>(),
             *glp = gl.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, in.count, 2048, [&](int64_t begin, int64_t end) {
      for (int64_t p = begin; p < end; ++p) {
        const int64_t e = p % per_scene;
        yield_adjoint_particle(xp + 3 * p, ap + 3 * p, lp[e], fp[e], gp + 3 * p, gxp + 3 * p,
                               gap + 3 * p, glp + p);
      }
    });
  });
  return {gx, ga, gl};
}

} // namespace
} // namespace frame
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::frame::kFinishAdjointSchema);
  m.def(ams_torch::frame::kYieldAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("finish_adjoint", &ams_torch::frame::finish_adjoint_cpu);
  m.impl("yield_adjoint", &ams_torch::frame::yield_adjoint_cpu);
}
