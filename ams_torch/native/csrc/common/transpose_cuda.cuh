// Batched tiled transpose for the CUDA kernels of csrc/frame and csrc/collide: converts every
// array of a call between torch's (strands, values) layout and the strand-interleaved one
// (value e of strand s at e · strands + s) in one launch, so that the per-strand kernels (one
// thread per strand) read and write consecutive addresses across a warp. CUDA only, no torch
// headers.
#pragma once

#include <cuda_runtime.h>

#include <stdint.h>

#include "common/launch_cuda.cuh"

namespace ams_torch {
namespace frame {

constexpr int kTile = 32;     // transpose tile edge
constexpr int kTileRows = 8;  // rows of threads per transpose block
constexpr int kMaxJobs = 24;  // arrays per batched transpose

// out[c, r] = in[r, c] for row-major in (rows, cols), for every job of the batch.
template <class T>
struct TransposeJob {
  const T* src;
  T* dst;
  int64_t rows, cols, first_tile;
};

template <class T>
struct TransposeBatch {
  TransposeJob<T> job[kMaxJobs];
  int count = 0;
  int64_t tiles = 0;
  // Add src (rows, cols) -> dst (cols, rows); empty arrays are skipped. At most kMaxJobs.
  bool add(const T* src, T* dst, int64_t rows, int64_t cols) {
    if (rows <= 0 || cols <= 0) return true;
    if (count >= kMaxJobs) return false;
    job[count] = TransposeJob<T>{src, dst, rows, cols, tiles};
    tiles += ((rows + kTile - 1) / kTile) * ((cols + kTile - 1) / kTile);
    ++count;
    return true;
  }
};

template <class T>
__global__ void transpose_batch_kernel(const TransposeBatch<T> batch) {
  __shared__ T tile[kTile][kTile + 1];
  for (int64_t t = blockIdx.x; t < batch.tiles; t += gridDim.x) {
    int j = 0;
    while (j + 1 < batch.count && batch.job[j + 1].first_tile <= t) ++j;
    const T* in = batch.job[j].src;
    T* out = batch.job[j].dst;
    const int64_t rows = batch.job[j].rows, cols = batch.job[j].cols;
    const int64_t local = t - batch.job[j].first_tile;
    const int64_t col_tiles = (cols + kTile - 1) / kTile;
    const int64_t r0 = (local / col_tiles) * kTile;
    const int64_t c0 = (local % col_tiles) * kTile;
    for (int k = threadIdx.y; k < kTile; k += kTileRows) {
      const int64_t r = r0 + k, c = c0 + threadIdx.x;
      if (r < rows && c < cols) tile[k][threadIdx.x] = in[r * cols + c];
    }
    __syncthreads();
    for (int k = threadIdx.y; k < kTile; k += kTileRows) {
      const int64_t c = c0 + k, r = r0 + threadIdx.x;
      if (r < rows && c < cols) out[c * rows + r] = tile[threadIdx.x][k];
    }
    __syncthreads();
  }
}

template <class T>
void launch_transpose(const TransposeBatch<T>& batch, cudaStream_t stream) {
  if (batch.tiles == 0) return;
  transpose_batch_kernel<T><<<cuda::grid_stride_blocks(batch.tiles, 1), dim3(kTile, kTileRows), 0, stream>>>(batch);
}

} // namespace frame
} // namespace ams_torch
