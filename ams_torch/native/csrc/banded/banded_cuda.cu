// CUDA kernel of the banded strand solve. One thread per strand runs the shared per-strand
// routine (banded_cholesky.h) on a strand-interleaved copy of the data, so that the 32 threads
// of a warp read and write 32 consecutive values at every step (coalesced). Tiled
// shared-memory transposes convert between torch's (strands, ...) layout and the interleaved
// one. No torch headers: see banded_cuda.h.
#include <cuda_runtime.h>

#include <stdint.h>

#include "banded/banded_cholesky.h"
#include "banded/banded_cuda.h"
#include "common/launch_cuda.cuh"

namespace ams_torch {
namespace banded {
namespace {

constexpr int kTile = 32;          // transpose tile edge
constexpr int kTileRows = 8;       // rows of threads per transpose block
constexpr int kSolveThreads = 128; // threads (strands) per solve block
// resident blocks per SM asked of the register allocator: 4 (<= 128 registers), 3 on sm_120+ (<= 170),
// whose allocator spills the double solve at 128 (ptxas: 224 bytes; tests/test_ptxas_budget.py)
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 1200
constexpr int kSolveMinBlocks = 3;
#else
constexpr int kSolveMinBlocks = 4;
#endif

// out[c, r] = in[r, c] for row-major `in` of shape (rows, cols). Grid-stride over 32×32 tiles.
template <class T>
__global__ void transpose_kernel(const T* __restrict__ in, T* __restrict__ out, int64_t rows, int64_t cols) {
  __shared__ T tile[kTile][kTile + 1];
  const int64_t col_tiles = (cols + kTile - 1) / kTile;
  const int64_t tiles = ((rows + kTile - 1) / kTile) * col_tiles;
  for (int64_t t = blockIdx.x; t < tiles; t += gridDim.x) {
    const int64_t r0 = (t / col_tiles) * kTile;
    const int64_t c0 = (t % col_tiles) * kTile;
    for (int j = threadIdx.y; j < kTile; j += kTileRows) {
      const int64_t r = r0 + j, c = c0 + threadIdx.x;
      if (r < rows && c < cols) tile[j][threadIdx.x] = in[r * cols + c];
    }
    __syncthreads();
    for (int j = threadIdx.y; j < kTile; j += kTileRows) {
      const int64_t c = c0 + j, r = r0 + threadIdx.x;
      if (r < rows && c < cols) out[c * rows + r] = tile[threadIdx.x][j];
    }
    __syncthreads();
  }
}

template <class T>
void launch_transpose(const T* in, T* out, int64_t rows, int64_t cols, cudaStream_t stream) {
  const int64_t tiles = ((rows + kTile - 1) / kTile) * ((cols + kTile - 1) / kTile);
  transpose_kernel<T><<<cuda::grid_stride_blocks(tiles, 1), dim3(kTile, kTileRows), 0, stream>>>(in, out, rows, cols);
}

// a: strand-interleaved matrix rows (n × 36 values per strand), factored in place;
// b: strand-interleaved right-hand sides (n × 3), overwritten by the solution.
template <class T>
__global__ void __launch_bounds__(kSolveThreads, kSolveMinBlocks) solve_kernel(T* a, T* b, int64_t strands, int64_t n) {
  const int64_t s = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (s >= strands) return;
  const Lanes<T, T> la{a + s, strands};
  const Lanes<T, T> lb{b + s, strands};
  solve_strand<T, T>(la, lb, n);
}

} // namespace

int64_t cuda_workspace_elems(int64_t strands, int64_t n) {
  return strands * n * (kRowElems + kRhsElems);
}

template <class T>
cudaError_t solve_banded_cuda(const T* blocks, const T* rhs, T* x, T* workspace, int64_t strands, int64_t n,
                              cudaStream_t stream) {
  if (strands <= 0 || n <= 0) return cudaSuccess;
  T* wa = workspace;
  T* wb = workspace + strands * n * kRowElems;
  launch_transpose<T>(blocks, wa, strands, n * kRowElems, stream); // (S, 36n) -> (36n, S)
  launch_transpose<T>(rhs, wb, strands, n * kRhsElems, stream);    // (S, 3n)  -> (3n, S)
  const int threads = cuda::strand_block_threads(strands, kSolveThreads); // small solves: 32/64 threads per block
  const int64_t grid = (strands + threads - 1) / threads;
  if (grid > 0x7fffffffLL) return cudaErrorInvalidConfiguration;
  solve_kernel<T><<<unsigned(grid), threads, 0, stream>>>(wa, wb, strands, n);
  launch_transpose<T>(wb, x, n * kRhsElems, strands, stream); // (3n, S) -> (S, 3n)
  return cudaGetLastError();
}

template cudaError_t solve_banded_cuda<float>(const float*, const float*, float*, float*, int64_t, int64_t,
                                              cudaStream_t);
template cudaError_t solve_banded_cuda<double>(const double*, const double*, double*, double*, int64_t, int64_t,
                                               cudaStream_t);

} // namespace banded
} // namespace ams_torch
