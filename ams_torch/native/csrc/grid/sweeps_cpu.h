// The pressure sweeps and their reverse on the host, on raw arrays (sweeps.h's layout): used by the
// ops `sweeps` / `sweeps_adjoint` (sweeps_cpu.cpp) and by the pressure's adjoint
// (grid_adjoint_cpu.cpp). A sweep's slots in parallel (at::parallel_for; each slot reads the previous
// φ, writes its own); the reverse runs the sweeps backwards from the kept history, the per-slot part
// in parallel, the scatter of φ̄ into the neighbours gathered by destination (each slot's incoming
// entries in index_add's order, direction-major), in parallel, so the sums are the torch definition's.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <vector>

#include "grid/sweeps.h"

namespace ams_torch {
namespace grid {
namespace host_sweeps {

constexpr int64_t kGrain = 2048;

// `iterations` sweeps from φ = 0 over n1 slots; history (iterations × n1, or nullptr) receives φ
// before each sweep, out (n1) the last φ.
template <class T>
void forward(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t n1, int64_t iterations, T keep,
             T* history, T* out) {
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

// The reverse of `forward` from its history, for the adjoint g0 (n1) of the last φ: accumulates
// into g_src, g_coef (n1) and g_w (6 × n1).
template <class T>
void reverse(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t n1, int64_t iterations, T keep,
             const T* history, const T* g0, T* g_src, T* g_coef, T* g_w) {
  std::vector<T> g(g0, g0 + n1);
  std::vector<T> t(static_cast<size_t>(n1));
  std::vector<T> g_phi(static_cast<size_t>(n1));
  // the scatter φ̄[nbr[e]] += w[e] t[e mod n1] by destination: each slot's incoming entries e in
  // ascending order (a counting sort of nbr), so every slot sums in index_add's order, in parallel
  const int64_t edges = kSweepDirs * n1;
  std::vector<int64_t> start(static_cast<size_t>(n1 + 1), 0);
  std::vector<int64_t> incoming(static_cast<size_t>(edges));
  for (int64_t e = 0; e < edges; ++e) ++start[size_t(nbr[e] + 1)];
  for (int64_t j = 0; j < n1; ++j) start[size_t(j + 1)] += start[size_t(j)];
  std::vector<int64_t> from(static_cast<size_t>(edges)); // the slot i of each incoming entry (e mod n1)
  {
    std::vector<int64_t> cursor(start.begin(), start.end() - 1);
    for (int64_t e = 0; e < edges; ++e) {
      const int64_t q = cursor[size_t(nbr[e])]++;
      incoming[size_t(q)] = e;
      from[size_t(q)] = e % n1;
    }
  }
  for (int64_t k = iterations - 1; k >= 0; --k) {
    const T* phi = history + k * n1;
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

} // namespace host_sweeps
} // namespace grid
} // namespace ams_torch
