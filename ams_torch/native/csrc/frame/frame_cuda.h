// Launcher of the CUDA fused frame kernel. Plain pointers and a cudaStream_t, no torch headers:
// frame_cuda.cu compiles with nvcc alone (CI compiles it on machines without a GPU), and the
// thin torch binding (frame_cuda_binding.cpp, built only against a CUDA torch) calls it on the
// current stream with a workspace from torch's caching allocator.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

#include "frame/finish.h"
#include "frame/frame.h"

namespace ams_torch {
namespace frame {

extern "C++" {

// Number of T elements of workspace `frame_cuda` needs for B scenes of S strands of N
// particles and M substeps: the substep poses (B (M + 1) 12), the per-strand inputs
// strand-interleaved (S (14 N − 13)), and per (scene, strand) the state, the matrix and the
// right-hand side strand-interleaved (B S 63 N).
int64_t frame_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t substeps);

// One frame (assemble_substep < 0: out0 = x', out1 = v', each (B, S, N, 3)) or one substep's
// system (assemble_substep = k: out0 = blocks (B, S, N, 4, 3, 3), out1 = rhs (B, S, N, 3)),
// asynchronously on `stream`. Launches: substep poses (one thread per scene and pose), one
// batched tiled transpose of every input into the workspace's strand-interleaved layout (value
// e of strand s at e · strands + s, so that consecutive threads read consecutive addresses), the
// frame kernel (one thread per (scene, strand), frame.h), one batched transpose of the two
// results back. Returns cudaGetLastError() after the last launch.
template <class T>
cudaError_t frame_cuda(const FrameArgs<T>& args, const FrameSettings& cfg, int64_t assemble_substep, T* out0, T* out1,
                       T* workspace, cudaStream_t stream);

extern template cudaError_t frame_cuda<float>(const FrameArgs<float>&, const FrameSettings&, int64_t, float*, float*,
                                              float*, cudaStream_t);
extern template cudaError_t frame_cuda<double>(const FrameArgs<double>&, const FrameSettings&, int64_t, double*,
                                               double*, double*, cudaStream_t);

// Bytes of the table of prepared colliders `frame_contact_cuda` needs (collide::Prepared<T>, one
// per scene, substep and collider; elem_bytes = sizeof(T)).
int64_t frame_contact_table_bytes(int64_t scenes, int64_t substeps, int64_t colliders, int64_t elem_bytes);

// One frame with substep contact (out0 = x', out1 = v'): the colliders of every scene and substep
// prepared into `table` (device memory of frame_contact_table_bytes, 16-byte aligned), then the
// launches of frame_cuda with the contact response after every substep (frame.h).
template <class T>
cudaError_t frame_contact_cuda(const FrameArgs<T>& args, const ContactArgs<T>& contact, const FrameSettings& cfg,
                               T* out0, T* out1, T* workspace, void* table, cudaStream_t stream);

extern template cudaError_t frame_contact_cuda<float>(const FrameArgs<float>&, const ContactArgs<float>&,
                                                      const FrameSettings&, float*, float*, float*, void*,
                                                      cudaStream_t);
extern template cudaError_t frame_contact_cuda<double>(const FrameArgs<double>&, const ContactArgs<double>&,
                                                       const FrameSettings&, double*, double*, double*, void*,
                                                       cudaStream_t);

// The frame's end (finish.h): one thread per particle, asynchronously on `stream`. Returns
// cudaGetLastError() after the launch.
template <class T>
cudaError_t finish_cuda(const FinishArgs<T>& args, cudaStream_t stream);

extern template cudaError_t finish_cuda<float>(const FinishArgs<float>&, cudaStream_t);
extern template cudaError_t finish_cuda<double>(const FinishArgs<double>&, cudaStream_t);

} // extern "C++"

} // namespace frame
} // namespace ams_torch
