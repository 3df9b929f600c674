// Launchers of the CUDA kernels of the differentiable frame (frame_adjoint.h): plain pointers and a
// cudaStream_t, no torch headers (frame_adjoint_cuda.cu compiles with nvcc alone); the torch binding
// (frame_adjoint_cuda_binding.cpp, built only against a CUDA torch) calls them on the current
// stream with a workspace from torch's caching allocator.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

#include "frame/frame.h"

namespace ams_torch {
namespace frame {

extern "C++" {

// Raw pointers of the adjoint's seeds and outputs (frame_adjoint_binding.h's layout): per scene and
// strand x̄, v̄, ḡ, ext̄ (B, S, N, 3; ext̄ null without an external force), mass̄, draḡ, integritȳ
// (B, S, N), stiffness̄ k (B, S, N − 1 − k), angular̄ (B, S, N − 1), poses̄ (B, S, M + 1, 12), sag̅
// (B, S, N, 3), the non-Hookean curve's (B, S, 3).
template <class T>
struct AdjointBuffers {
  const T *xb_in, *vb_in;
  T *xb, *vb, *gb, *extb, *massb, *dragb, *stiffb[3], *integrityb, *angularb, *poseb, *sagb, *lawb;
};

// Elements of T of workspace for B scenes of S strands of N particles and M substeps: the
// per-strand inputs and, per (scene, strand), the state, matrix, adjoint arrays and the states of
// the M + 1 substep starts, strand-interleaved (about S (14 N) + B S ((6 M + 100) N + 12 (M + 1))).
int64_t frame_adjoint_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t substeps);

// The frame with its substep poses given (poses: (P, M + 1, 12), P = 1 or B; adjoint == nullptr:
// x', v' into out_x, out_v) or its adjoint (adjoint != nullptr: seeds and outputs there). One
// batched transpose of the inputs into the workspace, one kernel (one thread per (scene, strand)),
// one batched transpose of the results back. Returns cudaGetLastError() after the last launch.
template <class T>
cudaError_t frame_adjoint_cuda(const FrameArgs<T>& args, const FrameSettings& cfg, const T* poses, int64_t pose_scenes,
                               T* out_x, T* out_v, const AdjointBuffers<T>* adjoint, T* workspace,
                               cudaStream_t stream);

extern template cudaError_t frame_adjoint_cuda<float>(const FrameArgs<float>&, const FrameSettings&, const float*,
                                                      int64_t, float*, float*, const AdjointBuffers<float>*, float*,
                                                      cudaStream_t);
extern template cudaError_t frame_adjoint_cuda<double>(const FrameArgs<double>&, const FrameSettings&, const double*,
                                                       int64_t, double*, double*, const AdjointBuffers<double>*,
                                                       double*, cudaStream_t);

} // extern "C++"

} // namespace frame
} // namespace ams_torch
