// Launcher of the CUDA banded strand solve. Plain pointers and a cudaStream_t, no torch
// headers: banded_cuda.cu compiles with nvcc alone (the CPU torch wheel has no CUDA build
// headers, and CI compiles the .cu on machines without a GPU), and the thin torch binding
// (banded_cuda_binding.cpp, built only against a CUDA torch) calls it on the current stream.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

namespace ams_torch {
namespace banded {

extern "C++" {

// Number of T elements of scratch `solve_banded_cuda` needs: strands × n × (36 + 3).
int64_t cuda_workspace_elems(int64_t strands, int64_t n);

// Solve A x = rhs for every strand, asynchronously on `stream`.
//   blocks: (strands, n, 4, 3, 3) contiguous, blocks[s, i, k] = A_s[i, i-k] (banded_cholesky.h)
//   rhs, x: (strands, n, 3) contiguous; x may not alias blocks or rhs
//   workspace: cuda_workspace_elems(strands, n) elements of device memory
// The blocks and rhs are transposed into the workspace in a strand-interleaved layout (value e
// of strand s at e × strands + s), so that consecutive threads (= consecutive strands) of the
// solve kernel read consecutive addresses; the factor is computed in place there.
// Returns the launch status (cudaGetLastError after the last launch).
template <class T>
cudaError_t solve_banded_cuda(const T* blocks, const T* rhs, T* x, T* workspace, int64_t strands, int64_t n,
                              cudaStream_t stream);

extern template cudaError_t solve_banded_cuda<float>(const float*, const float*, float*, float*, int64_t, int64_t,
                                                     cudaStream_t);
extern template cudaError_t solve_banded_cuda<double>(const double*, const double*, double*, double*, int64_t,
                                                      int64_t, cudaStream_t);

} // extern "C++"

} // namespace banded
} // namespace ams_torch
