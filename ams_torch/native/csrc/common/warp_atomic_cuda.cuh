// Warp-aggregated atomic add (device code, no torch headers). The lanes of a warp that add to the
// same address combine their values first (__match_any_sync groups them, the group's lowest lane
// sums its peers' values in lane order with __shfl_sync) and one atomicAdd per group goes to
// memory. For scatters where a warp's lanes often hit the same address (P2G: consecutive
// particles of a strand share grid faces) this divides the atomics on contended addresses by the
// group size, for one match and popc(group) shuffles per call. Needs sm_70+ (every architecture
// nvcc 13 builds); the sum order within a group is fixed, across groups and warps it is not (the
// result's last bits vary between runs, as with plain atomics).
#pragma once

#include <cuda_runtime.h>

namespace ams_torch {
namespace cuda {

__device__ __forceinline__ unsigned lane_id() {
  const unsigned linear = (threadIdx.z * blockDim.y + threadIdx.y) * blockDim.x + threadIdx.x;
  return linear % 32u;
}

template <class T>
__device__ __forceinline__ void warp_aggregated_add(T* address, T value) {
  const unsigned active = __activemask();
  const unsigned peers = __match_any_sync(active, reinterpret_cast<unsigned long long>(address));
  const unsigned leader = unsigned(__ffs(int(peers)) - 1);
  T sum = T(0);
  for (unsigned rest = peers; rest != 0u; rest &= rest - 1u) {
    const T other = __shfl_sync(peers, value, __ffs(int(rest)) - 1);
    sum += other;
  }
  if (lane_id() == leader) atomicAdd(address, sum);
}

} // namespace cuda
} // namespace ams_torch
