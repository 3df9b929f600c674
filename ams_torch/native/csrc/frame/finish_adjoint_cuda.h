// Launchers of the CUDA finish and yield adjoints (finish_adjoint.h). Plain pointers and a
// cudaStream_t, no torch headers: finish_adjoint_cuda.cu compiles with nvcc alone; the binding
// (finish_adjoint_cuda_binding.cpp, built only against a CUDA torch) calls them on the current stream.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

#include "frame/finish.h"

namespace ams_torch {
namespace frame {

extern "C++" {

// One thread per strand: g_x, g_v (B S N 3) and g_pose (B S, 9) from g_out and g_speed (or null).
template <class T>
cudaError_t finish_adjoint_cuda(const FinishArgs<T>& args, const T* g_out, const T* g_speed, T* g_x, T* g_v,
                                T* g_pose, cudaStream_t stream);

// One thread per particle: g_x, g_anchor (count 3), g_limit (count); limit and free (S N).
template <class T>
cudaError_t yield_adjoint_cuda(const T* x, const T* anchor, const T* limit, const bool* free, const T* g_new, T* g_x,
                               T* g_anchor, T* g_limit, int64_t count, int64_t strands, int64_t particles,
                               cudaStream_t stream);

} // extern "C++"

} // namespace frame
} // namespace ams_torch
