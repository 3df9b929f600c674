// Launcher of the CUDA fused collision stage. Plain pointers and a cudaStream_t, no torch
// headers: collide_cuda.cu compiles with nvcc alone, and the thin torch binding
// (collide_cuda_binding.cpp, built only against a CUDA torch) calls it on the current stream with
// a workspace from torch's caching allocator.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

#include "collide/collide.h"

namespace ams_torch {
namespace collide {

extern "C++" {

// Number of T elements of workspace `collide_cuda` needs: the colliders' per-scene values
// (B C Prepared<T>), x and v per (scene, strand) and the rest shape and edge lengths per strand,
// strand-interleaved.
int64_t collide_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t colliders,
                                     int64_t elem_bytes);

// The whole collision stage, xo, vo (B, S, N, 3), asynchronously on `stream`. Launches: collider
// preparation (one thread per scene and collider), one batched transpose of the inputs into the
// strand-interleaved workspace, the stage (one thread per (scene, strand), collide.h), one
// batched transpose of x, v back. Returns cudaGetLastError() after the last launch.
template <class T>
cudaError_t collide_cuda(const CollideArgs<T>& args, const CollideSettings& cfg, T* xo, T* vo, T* workspace,
                         cudaStream_t stream);

extern template cudaError_t collide_cuda<float>(const CollideArgs<float>&, const CollideSettings&, float*, float*,
                                                float*, cudaStream_t);
extern template cudaError_t collide_cuda<double>(const CollideArgs<double>&, const CollideSettings&, double*,
                                                 double*, double*, cudaStream_t);

} // extern "C++"

} // namespace collide
} // namespace ams_torch
