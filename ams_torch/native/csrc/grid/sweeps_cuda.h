// Launchers of the CUDA pressure sweeps and their adjoint. Plain pointers and a cudaStream_t, no
// torch headers: sweeps_cuda.cu compiles with nvcc alone; sweeps_cuda_binding.cpp (built only
// against a CUDA torch) calls them on the current stream with workspaces from torch's allocator.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

namespace ams_torch {
namespace grid {

extern "C++" {

// Workspace elements (of T) of sweeps_cuda (2 (L + 1)) and sweeps_adjoint_cuda
// ((iterations + 4) (L + 1)).
int64_t sweeps_cuda_workspace_elems(int64_t slots, int64_t iterations, bool adjoint);

// φ (L + 1) after `iterations` sweeps from 0 (sweeps.h): one launch per sweep, a thread per slot.
template <class T>
cudaError_t sweeps_cuda(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t slots,
                        int64_t iterations, T keep, T* out, T* workspace, cudaStream_t stream);

// The adjoints of src, coef, w (zeroed by the caller) for the adjoint g of φ: the sweeps again
// keeping φ before each, then per sweep in reverse a launch per slot and a scatter launch
// (atomicAdd: the sums' order, hence the last bits, vary between runs).
template <class T>
cudaError_t sweeps_adjoint_cuda(const T* src, const T* coef, const T* w, const int64_t* nbr, int64_t slots,
                                int64_t iterations, T keep, const T* g, T* g_src, T* g_coef, T* g_w, T* workspace,
                                cudaStream_t stream);

} // extern "C++"

} // namespace grid
} // namespace ams_torch
