// CUDA kernel of the collision stage's adjoint: one thread per (scene, strand) runs
// collide_adjoint.h (the CPU kernel runs the same code on SIMD lanes). As the forward
// (collide_cuda.cu): the inputs are transposed once into a strand-interleaved workspace (coalesced
// accesses of a warp), x̄ and v̄ back at the end; the colliders' per-scene values are prepared once
// per call. Each thread writes its strand's pose adjoints (C × 19) and the head rotation's (9); the
// torch side sums them over strands (deterministic, no atomics). No torch headers: see
// collide_adjoint_cuda.h.
#include <cuda_runtime.h>

#include <stdint.h>

#include "collide/collide_adjoint.h"
#include "collide/collide_adjoint_cuda.h"
#include "collide/collide_table_cuda.cuh"
#include "common/launch_cuda.cuh"
#include "common/transpose_cuda.cuh"

namespace ams_torch {
namespace collide {
namespace {

constexpr int kAdjointThreads = 64;

template <class T>
__global__ void __launch_bounds__(kAdjointThreads) adjoint_kernel(const CollideArgs<T> args, const CollideSettings cfg,
                                                                    const Prepared<T>* table, T* hist, T* xb, T* vb,
                                                                    T* xb_new, T* lam, T* rest, T* edge, T* gcol,
                                                                    T* ghead) {
  const int64_t S = args.strands, N = args.particles, G = args.scenes * S, C = args.count;
  const int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (g >= G) return;
  const int64_t b = g / S, s = g % S;
  int64_t p = args.num_pinned[s];
  p = p < 0 ? 0 : (p > N ? N : p);
  const T* head = args.head_rotation + 9 * (args.head_scenes == 1 ? 0 : b);
  const StageAdjoint<T, T> w{Lanes<T, T>{hist + g, G}, Lanes<T, T>{xb + g, G}, Lanes<T, T>{vb + g, G},
                             Lanes<T, T>{xb_new + g, G}, Lanes<T, T>{lam + g, G}};
  T acc[kMaxColliders * kPoseGrads];
  for (int64_t k = 0; k < C * kPoseGrads; ++k) acc[k] = T(0);
  T headb[9];
  for (int e = 0; e < 9; ++e) headb[e] = T(0);
  collision_stage_adjoint<T, T>(w, Lanes<T, T>{rest + s, S}, Lanes<T, T>{edge + s, S}, N, T(p), table + b * C, int(C),
                                cfg, head, acc, headb);
  for (int64_t k = 0; k < C * kPoseGrads; ++k) gcol[g * C * kPoseGrads + k] = acc[k];
  for (int e = 0; e < 9; ++e) ghead[g * 9 + e] = headb[e];
}

} // namespace

int64_t collide_adjoint_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t colliders,
                                             int64_t rounds, int64_t elem_bytes) {
  const int64_t prepared = elem_bytes == 4 ? int64_t(sizeof(Prepared<float>)) : int64_t(sizeof(Prepared<double>));
  const int64_t G = scenes * strands;
  return table_elems(scenes, colliders, elem_bytes, prepared) + (6 * (1 + 2 * rounds) + 12) * particles * G +
         (4 * particles - 1) * strands;
}

template <class T>
cudaError_t collide_adjoint_cuda(const CollideArgs<T>& args, const CollideSettings& cfg, const T* gx, const T* gv,
                                 T* gxo, T* gvo, T* gcol, T* ghead, T* workspace, cudaStream_t stream) {
  const int64_t B = args.scenes, S = args.strands, N = args.particles, G = B * S, C = args.count;
  if (G <= 0) return cudaSuccess;
  const int rounds = cfg.inextensibility ? cfg.rounds : 0;
  Prepared<T>* table = reinterpret_cast<Prepared<T>*>(workspace);
  T* hist = workspace + table_elems(B, C, int64_t(sizeof(T)), int64_t(sizeof(Prepared<T>)));
  T* xb = hist + 6 * N * (1 + 2 * rounds) * G;
  T* vb = xb + 3 * N * G;
  T* xb_new = vb + 3 * N * G;
  T* lam = xb_new + 3 * N * G;
  T* rest = lam + 3 * N * G;
  T* edge = rest + 3 * N * S;
  launch_prepare(args, table, stream);
  frame::TransposeBatch<T> in; // snapshot 0 of the history: x then v
  in.add(args.x, hist, G, 3 * N);
  in.add(args.v, hist + 3 * N * G, G, 3 * N);
  in.add(gx, xb, G, 3 * N);
  in.add(gv, vb, G, 3 * N);
  if (rounds > 0) {
    in.add(args.rest_positions, rest, S, 3 * N);
    in.add(args.edge_rest_length, edge, S, N - 1);
  }
  frame::launch_transpose(in, stream);
  const int threads = cuda::strand_block_threads(G, kAdjointThreads);
  const int64_t grid = (G + threads - 1) / threads;
  if (grid > 0x7fffffffLL) return cudaErrorInvalidConfiguration;
  adjoint_kernel<T><<<unsigned(grid), threads, 0, stream>>>(args, cfg, table, hist, xb, vb, xb_new, lam, rest, edge,
                                                            gcol, ghead);
  frame::TransposeBatch<T> back;
  back.add(xb, gxo, 3 * N, G);
  back.add(vb, gvo, 3 * N, G);
  frame::launch_transpose(back, stream);
  return cudaGetLastError();
}

template cudaError_t collide_adjoint_cuda<float>(const CollideArgs<float>&, const CollideSettings&, const float*,
                                                 const float*, float*, float*, float*, float*, float*, cudaStream_t);
template cudaError_t collide_adjoint_cuda<double>(const CollideArgs<double>&, const CollideSettings&, const double*,
                                                  const double*, double*, double*, double*, double*, double*,
                                                  cudaStream_t);

} // namespace collide
} // namespace ams_torch
