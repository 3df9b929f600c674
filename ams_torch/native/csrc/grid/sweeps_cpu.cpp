// CPU kernels of the pressure sweeps and their adjoint: ops `ams_torch_cpu::sweeps` and
// `sweeps_adjoint` (schemas in sweeps_binding.h, arithmetic in sweeps.h). A sweep's slots in
// parallel (at::parallel_for; each slot reads the previous φ, writes its own); the adjoint keeps φ
// before each sweep (iterations × (L + 1) values), then runs the sweeps in reverse: the per-slot
// part in parallel, the scatter of φ̄ into the neighbours gathered by destination (each slot's
// incoming entries in index_add's order, direction-major), in parallel, so the sums are the torch
// definition's.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <tuple>
#include <vector>

#include "grid/sweeps.h"
#include "grid/sweeps_binding.h"

namespace ams_torch {
namespace grid {
namespace {

constexpr int64_t kGrain = 2048;

template <class T>
void run_sweeps(const SweepsInputs& in, int64_t iterations, T keep, T* history, T* out) {
  const int64_t n1 = in.slots;
  const T* src = in.src.const_data_ptr<T>();
  const T* coef = in.coef.const_data_ptr<T>();
  const T* w = in.w.const_data_ptr<T>();
  const int64_t* nbr = in.nbr.const_data_ptr<int64_t>();
  std::vector<T> buf(static_cast<size_t>(n1), T(0));
  T* cur = buf.data();
  std::vector<T> nxt(static_cast<size_t>(n1));
  for (int64_t k = 0; k < iterations; ++k) {
    if (history != nullptr) std::copy(cur, cur + n1, history + k * n1);
    at::parallel_for(0, n1, kGrain, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) nxt[size_t(i)] = sweep_cell(i, n1, src, coef, w, nbr, cur, keep);
    });
    std::copy(nxt.begin(), nxt.end(), cur);
  }
  std::copy(cur, cur + n1, out);
}

at::Tensor sweeps_cpu(const at::Tensor& src, const at::Tensor& coef, const at::Tensor& w, const at::Tensor& nbr,
                      int64_t iterations, double omega) {
  constexpr const char* op = "ams_torch_cpu::sweeps";
  const SweepsInputs in = check_sweeps_inputs(op, src, coef, w, nbr, iterations, nullptr);
  TORCH_CHECK(in.src.device().is_cpu(), op, ": CPU tensors expected");
  at::Tensor out = at::empty({in.slots}, in.src.options());
  AT_DISPATCH_FLOATING_TYPES(in.src.scalar_type(), op, [&] {
    run_sweeps<scalar_t>(in, iterations, scalar_t(1.0 - omega), nullptr, out.mutable_data_ptr<scalar_t>());
  });
  return out;
}

template <class T>
void run_adjoint(const SweepsInputs& in, int64_t iterations, T keep, T* g_src, T* g_coef, T* g_w) {
  const int64_t n1 = in.slots;
  std::vector<T> history(static_cast<size_t>(iterations * n1));
  std::vector<T> last(static_cast<size_t>(n1));
  run_sweeps<T>(in, iterations, keep, history.data(), last.data());
  const T* src = in.src.const_data_ptr<T>();
  const T* coef = in.coef.const_data_ptr<T>();
  const T* w = in.w.const_data_ptr<T>();
  const int64_t* nbr = in.nbr.const_data_ptr<int64_t>();
  const T* g0 = in.g.const_data_ptr<T>();
  std::vector<T> g(g0, g0 + n1);
  std::vector<T> t(static_cast<size_t>(n1));
  std::vector<T> g_phi(static_cast<size_t>(n1));
  // the scatter φ̄[nbr[e]] += w[e] t[e mod (L + 1)] by destination: each slot's incoming entries e in
  // ascending order (a counting sort of nbr), so every slot sums in index_add's order, in parallel
  const int64_t edges = kSweepDirs * n1;
  std::vector<int64_t> start(static_cast<size_t>(n1 + 1), 0);
  std::vector<int64_t> incoming(static_cast<size_t>(edges));
  for (int64_t e = 0; e < edges; ++e) ++start[size_t(nbr[e] + 1)];
  for (int64_t j = 0; j < n1; ++j) start[size_t(j + 1)] += start[size_t(j)];
  std::vector<int64_t> from(static_cast<size_t>(edges)); // the slot i of each incoming entry (e mod (L + 1))
  {
    std::vector<int64_t> cursor(start.begin(), start.end() - 1);
    for (int64_t e = 0; e < edges; ++e) {
      const int64_t q = cursor[size_t(nbr[e])]++;
      incoming[size_t(q)] = e;
      from[size_t(q)] = e % n1;
    }
  }
  for (int64_t k = iterations - 1; k >= 0; --k) {
    const T* phi = history.data() + k * n1;
    at::parallel_for(0, n1, kGrain, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        sweep_cell_adjoint(i, n1, src, coef, w, nbr, phi, keep, g.data(), g_src, g_coef, g_w, t.data(), g_phi.data());
    });
    at::parallel_for(0, n1, kGrain, [&](int64_t b, int64_t e) {
      for (int64_t j = b; j < e; ++j) {
        T acc = g_phi[size_t(j)];
        for (int64_t q = start[size_t(j)]; q < start[size_t(j + 1)]; ++q)
          acc += w[incoming[size_t(q)]] * t[size_t(from[size_t(q)])];
        g_phi[size_t(j)] = acc;
      }
    });
    g.swap(g_phi);
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sweeps_adjoint_cpu(const at::Tensor& src, const at::Tensor& coef,
                                                                  const at::Tensor& w, const at::Tensor& nbr,
                                                                  int64_t iterations, double omega,
                                                                  const at::Tensor& g) {
  constexpr const char* op = "ams_torch_cpu::sweeps_adjoint";
  const SweepsInputs in = check_sweeps_inputs(op, src, coef, w, nbr, iterations, &g);
  TORCH_CHECK(in.src.device().is_cpu(), op, ": CPU tensors expected");
  at::Tensor g_src = at::zeros({in.slots}, in.src.options()), g_coef = at::zeros({in.slots}, in.src.options());
  at::Tensor g_w = at::zeros({kSweepDirs, in.slots}, in.src.options());
  AT_DISPATCH_FLOATING_TYPES(in.src.scalar_type(), op, [&] {
    run_adjoint<scalar_t>(in, iterations, scalar_t(1.0 - omega), g_src.mutable_data_ptr<scalar_t>(),
                          g_coef.mutable_data_ptr<scalar_t>(), g_w.mutable_data_ptr<scalar_t>());
  });
  return {g_src, g_coef, g_w.reshape(w.sizes())};
}

} // namespace
} // namespace grid
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::grid::kSweepsSchema);
  m.def(ams_torch::grid::kSweepsAdjointSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("sweeps", &ams_torch::grid::sweeps_cpu);
  m.impl("sweeps_adjoint", &ams_torch::grid::sweeps_adjoint_cpu);
}
