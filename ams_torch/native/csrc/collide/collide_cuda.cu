// CUDA kernel of the fused collision stage: one thread per (scene, strand) runs collide.h (the
// CPU kernel runs the same code on SIMD lanes). As in the fused frame (frame_cuda.cu), x and v
// (and the rest shape and edge lengths that follow-the-leader reads) are transposed once into a
// strand-interleaved workspace so that every access of a warp is coalesced, and x, v back at the
// end; the colliders' per-scene values (poses, offsets, geometry) are prepared once per call in a
// small table that every thread of a scene reads (broadcast). The mesh grid is read directly
// (trilinear gathers, cached). No torch headers: see collide_cuda.h.
#include <cuda_runtime.h>

#include <stdint.h>

#include "collide/collide.h"
#include "collide/collide_cuda.h"
#include "collide/collide_table_cuda.cuh"
#include "common/launch_cuda.cuh"
#include "common/transpose_cuda.cuh"

namespace ams_torch {
namespace collide {
namespace {

constexpr int kStageThreads = 128;

template <class T>
__global__ void __launch_bounds__(kStageThreads) stage_kernel(const CollideArgs<T> args, const CollideSettings cfg,
                                                                const Prepared<T>* table, T* x, T* v, T* rest,
                                                                T* edge) {
  const int64_t S = args.strands, N = args.particles, G = args.scenes * S;
  const int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (g >= G) return;
  const int64_t b = g / S, s = g % S;
  int64_t p = args.num_pinned[s];
  p = p < 0 ? 0 : (p > N ? N : p);
  const T* head = args.head_rotation + 9 * (args.head_scenes == 1 ? 0 : b);
  collision_stage<T, T>(Lanes<T, T>{x + g, G}, Lanes<T, T>{v + g, G}, Lanes<T, T>{rest + s, S},
                        Lanes<T, T>{edge + s, S}, N, T(p), table + b * args.count, args.count, cfg, head);
}

} // namespace

int64_t collide_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t colliders,
                                     int64_t elem_bytes) {
  const int64_t prepared = elem_bytes == 4 ? int64_t(sizeof(Prepared<float>)) : int64_t(sizeof(Prepared<double>));
  const int64_t G = scenes * strands;
  return table_elems(scenes, colliders, elem_bytes, prepared) + 6 * particles * G + (4 * particles - 1) * strands;
}

template <class T>
cudaError_t collide_cuda(const CollideArgs<T>& args, const CollideSettings& cfg, T* xo, T* vo, T* workspace,
                         cudaStream_t stream) {
  const int64_t B = args.scenes, S = args.strands, N = args.particles, G = B * S, C = args.count;
  if (G <= 0) return cudaSuccess;
  Prepared<T>* table = reinterpret_cast<Prepared<T>*>(workspace);
  T* x = workspace + table_elems(B, C, int64_t(sizeof(T)), int64_t(sizeof(Prepared<T>)));
  T* v = x + 3 * N * G;
  T* rest = v + 3 * N * G;
  T* edge = rest + 3 * N * S;
  launch_prepare(args, table, stream);
  frame::TransposeBatch<T> in;
  in.add(args.x, x, G, 3 * N);
  in.add(args.v, v, G, 3 * N);
  if (cfg.inextensibility && cfg.rounds > 0) {
    in.add(args.rest_positions, rest, S, 3 * N);
    in.add(args.edge_rest_length, edge, S, N - 1);
  }
  frame::launch_transpose(in, stream);
  const int threads = cuda::strand_block_threads(G, kStageThreads);
  const int64_t grid = (G + threads - 1) / threads;
  if (grid > 0x7fffffffLL) return cudaErrorInvalidConfiguration;
  stage_kernel<T><<<unsigned(grid), threads, 0, stream>>>(args, cfg, table, x, v, rest, edge);
  frame::TransposeBatch<T> back;
  back.add(x, xo, 3 * N, G);
  back.add(v, vo, 3 * N, G);
  frame::launch_transpose(back, stream);
  return cudaGetLastError();
}

template cudaError_t collide_cuda<float>(const CollideArgs<float>&, const CollideSettings&, float*, float*, float*,
                                         cudaStream_t);
template cudaError_t collide_cuda<double>(const CollideArgs<double>&, const CollideSettings&, double*, double*,
                                          double*, cudaStream_t);

} // namespace collide
} // namespace ams_torch
