// Host helpers of the CPU grid kernels (grid_cpu.cpp, grid_adjoint_cpu.cpp): bits of a slot's 64-cell
// masks (bit l: cell l) and the sweeps' waking of slots. Host only.
#pragma once

#include <stdint.h>

#include <vector>

namespace ams_torch {
namespace grid {

// The index of the lowest set bit (bits != 0).
inline int lowest_bit(uint64_t bits) {
#if defined(__GNUC__)
  return __builtin_ctzll(bits);
#else
  int l = 0;
  while (!(bits & 1)) {
    bits >>= 1;
    ++l;
  }
  return l;
#endif
}

// The number of set bits.
inline int popcount(uint64_t bits) {
#if defined(__GNUC__)
  return __builtin_popcountll(bits);
#else
  int n = 0;
  for (; bits; bits &= bits - 1) ++n;
  return n;
#endif
}

// The used slots of every scene, numbered u = first[b] + slot (slot < min(count[b], K)): first (B + 1)
// and, when `scene` is given, the scene of each of the first[B] slots.
inline std::vector<int64_t> used_slots(const int32_t* count, int64_t B, int64_t K,
                                       std::vector<int32_t>* scene = nullptr) {
  std::vector<int64_t> first(size_t(B + 1), 0);
  for (int64_t b = 0; b < B; ++b) {
    const int64_t n = count[b] < 0 ? 0 : (count[b] < K ? count[b] : K);
    first[size_t(b + 1)] = first[size_t(b)] + n;
  }
  if (scene != nullptr) {
    scene->assign(size_t(first[size_t(B)]), 0);
    for (int64_t b = 0; b < B; ++b)
      for (int64_t u = first[size_t(b)]; u < first[size_t(b + 1)]; ++u) (*scene)[size_t(u)] = int32_t(b);
  }
  return first;
}

// The Jacobi sweeps' waking (grid_cpu.cpp's pressure, grid_adjoint_cpu.cpp's pressure adjoint): after a
// sweep over the slots list[0, n), every neighbour slot (nbr: 6 per slot, within its scene, -1 none;
// first[scene[u]] + slot is its global index) of a slot whose phi became non-zero (live) that is
// not awake yet becomes awake and joins the list.
inline void wake_neighbours(std::vector<int64_t>& list, int64_t n, const std::vector<uint8_t>& live,
                            std::vector<uint8_t>& awake, const int32_t* nbr, const int64_t* first,
                            const int32_t* scene) {
  for (int64_t i = 0; i < n; ++i) {
    const int64_t u = list[size_t(i)];
    if (!live[size_t(u)]) continue;
    for (int d = 0; d < 6; ++d) {
      const int32_t s = nbr[6 * u + d];
      if (s < 0) continue;
      const int64_t w = first[scene[u]] + s;
      if (!awake[size_t(w)]) {
        awake[size_t(w)] = 1;
        list.push_back(w);
      }
    }
  }
}

} // namespace grid
} // namespace ams_torch
