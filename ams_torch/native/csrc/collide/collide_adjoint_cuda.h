// Launcher of the CUDA adjoint of the collision stage. Plain pointers and a cudaStream_t, no torch
// headers: collide_adjoint_cuda.cu compiles with nvcc alone, and the thin torch binding
// (collide_adjoint_cuda_binding.cpp, built only against a CUDA torch) calls it on the current
// stream with a workspace from torch's caching allocator.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

#include "collide/collide.h"

namespace ams_torch {
namespace collide {

extern "C++" {

// Number of T elements of workspace `collide_adjoint_cuda` needs: the colliders' per-scene values,
// per (scene, strand) the history of the stage's sub-stage inputs (6 N (1 + 2 rounds)) and four
// adjoint arrays (12 N), per strand the rest shape and edge lengths, strand-interleaved.
int64_t collide_adjoint_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t colliders,
                                             int64_t rounds, int64_t elem_bytes);

// x̄, v̄ (B, S, N, 3) of the stage's input for output adjoints gx, gv (B, S, N, 3), and per
// (scene, strand) the pose and friction adjoints gcol (B, S, C, 19) and the head rotation's ghead
// (B, S, 9), asynchronously on `stream`. Launches: collider preparation, one batched transpose in,
// the adjoint (one thread per (scene, strand), collide_adjoint.h), one batched transpose out.
template <class T>
cudaError_t collide_adjoint_cuda(const CollideArgs<T>& args, const CollideSettings& cfg, const T* gx, const T* gv,
                                 T* gxo, T* gvo, T* gcol, T* ghead, T* workspace, cudaStream_t stream);

extern template cudaError_t collide_adjoint_cuda<float>(const CollideArgs<float>&, const CollideSettings&,
                                                        const float*, const float*, float*, float*, float*, float*,
                                                        float*, cudaStream_t);
extern template cudaError_t collide_adjoint_cuda<double>(const CollideArgs<double>&, const CollideSettings&,
                                                         const double*, const double*, double*, double*, double*,
                                                         double*, double*, cudaStream_t);

} // extern "C++"

} // namespace collide
} // namespace ams_torch
