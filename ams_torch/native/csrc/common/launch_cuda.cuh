// Launch configuration shared by the CUDA kernels of csrc/ (no torch headers; host code).
//
//   grid_stride_blocks(work, threads): the grid of a grid-stride kernel: enough blocks to cover
//     the work, at most 2^20 (the kernels loop over the rest). Under the CUDA emulation of the
//     tests (csrc/emulation) the cap can be lowered with AMS_TORCH_EMU_MAX_GRID, so that the tests
//     run the stride loops with small inputs.
//   strand_block_threads(strands, max_threads): threads per block of a one-thread-per-strand
//     kernel: max_threads (the kernel's __launch_bounds__), halved down to 32 while that leaves
//     fewer than 4 blocks per multiprocessor. Small scenes (a few thousand strands) then spread
//     over every SM instead of filling a few: 32 threads below 4 × SMs × 64 strands, 64 below
//     4 × SMs × 128 (an H100 SXM, 132 SMs: 32 below 33,792 strands, 64 below 67,584).
#pragma once

#include <cuda_runtime.h>

#include <stdint.h>

#include <atomic>

namespace ams_torch {
namespace cuda {

constexpr int64_t kMaxGridStrideBlocks = int64_t(1) << 20;

inline unsigned grid_stride_blocks(int64_t work, int threads, int64_t cap = kMaxGridStrideBlocks) {
#if defined(AMS_TORCH_CUDA_EMULATION)
  const long emulated = ams_emu::env_long("AMS_TORCH_EMU_MAX_GRID", 0);
  if (emulated > 0 && emulated < cap) cap = emulated;
#endif
  const int64_t blocks = (work + threads - 1) / threads;
  return unsigned(blocks < 1 ? 1 : (blocks < cap ? blocks : cap));
}

// Multiprocessors of the current device (asked once per device; the emulation asks every time:
// its device is set by the environment).
inline int multiprocessor_count() {
  int device = 0;
  if (cudaGetDevice(&device) != cudaSuccess || device < 0) device = 0;
#if defined(AMS_TORCH_CUDA_EMULATION)
  int sms = 0;
  cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device);
  return sms > 0 ? sms : 1;
#else
  static std::atomic<int> known[64] = {};
  const int slot = device < 64 ? device : 63;
  int sms = known[slot].load(std::memory_order_relaxed);
  if (sms <= 0) {
    if (cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device) != cudaSuccess || sms <= 0) {
      cudaGetLastError();  // not sticky: clear it, and assume a large device
      return 128;
    }
    known[slot].store(sms, std::memory_order_relaxed);
  }
  return sms;
#endif
}

inline int strand_block_threads(int64_t strands, int max_threads) {
  const int64_t want = 4 * int64_t(multiprocessor_count());
  int threads = max_threads;
  while (threads > 32 && (strands + threads - 1) / threads < want) threads /= 2;
  return threads;
}

} // namespace cuda
} // namespace ams_torch
