// CUDA kernels of the differentiable frame: the fused frame with its substep poses given, and its
// adjoint (frame_adjoint.h; the CPU kernel runs the same per-strand code on SIMD lanes). One thread
// per (scene, strand). As frame_cuda.cu: the inputs are transposed once per call into a
// strand-interleaved copy in the workspace (value e of strand s at e · strands + s), so that the 32
// threads of a warp read and write 32 consecutive values at every step, and the results are
// transposed back. The adjoint's per-thread arrays (the states of the M + 1 substep starts, the
// adjoints) live in the workspace in the same layout. No torch headers: see frame_adjoint_cuda.h.
#include <cuda_runtime.h>

#include <stdint.h>

#include "frame/frame_adjoint.h"
#include "frame/frame_adjoint_cuda.h"
#include "common/transpose_cuda.cuh"

namespace ams_torch {
namespace frame {
namespace {

constexpr int kAdjointThreads = 64; // (scene, strand) threads per block: the adjoint holds more registers

// Workspace arrays (offsets in elements of T; model arrays hold count × strands values, scene
// arrays count × scenes × strands).
struct AdjointOffsets {
  int64_t rest, mass, drag, stiffness[3], rest_length[3], integrity, angular, segment;
  int64_t x, v, ghost_rest, sag_offset, ext, a, b, force, ghost, ghost_velocity;
  int64_t hist_x, hist_v, xb, vb, xb_new, vb_new, lam, ya, yb, wb, vpb, gb, extb, massb, dragb, integrityb;
  int64_t stiffb[3], angularb, poseb, sagb, lawb, total;
  AdjointOffsets(int64_t B, int64_t S, int64_t N, int64_t M) {
    const int64_t G = B * S;
    int64_t o = 0;
    auto take = [&o](int64_t count) {
      const int64_t at = o;
      o += count;
      return at;
    };
    rest = take(3 * N * S);
    mass = take(N * S);
    drag = take(N * S);
    for (int k = 0; k < 3; ++k) stiffness[k] = take((N - 1 - k) * S);
    for (int k = 0; k < 3; ++k) rest_length[k] = take((N - 1 - k) * S);
    integrity = take(N * S);
    angular = take((N - 1) * S);
    segment = take(N * S);
    for (int64_t* f : {&x, &v, &ghost_rest, &sag_offset, &ext}) *f = take(3 * N * G);
    a = take(banded::kRowElems * N * G);
    for (int64_t* f : {&b, &force, &ghost, &ghost_velocity}) *f = take(3 * N * G);
    hist_x = take(3 * N * (M + 1) * G);
    hist_v = take(3 * N * (M + 1) * G);
    for (int64_t* f : {&xb, &vb, &xb_new, &vb_new, &lam, &ya, &yb, &wb, &vpb, &gb, &extb}) *f = take(3 * N * G);
    for (int64_t* f : {&massb, &dragb, &integrityb}) *f = take(N * G);
    for (int k = 0; k < 3; ++k) stiffb[k] = take((N - 1 - k) * G);
    angularb = take((N - 1) * G);
    poseb = take(int64_t(kPoseElems) * (M + 1) * G);
    sagb = take(3 * N * G);
    lawb = take(3 * G);
    total = o;
  }
};

template <class T>
__global__ void __launch_bounds__(kAdjointThreads)
    adjoint_kernel(const FrameArgs<T> args, const FrameSettings cfg, const T* poses, int64_t pose_scenes, T* w,
                   const AdjointOffsets off, bool adjoint) {
  const int64_t S = args.strands, N = args.particles, G = args.scenes * S;
  const int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (g >= G) return;
  const int64_t b = g / S, s = g % S;
  auto per_strand = [&](int64_t o) { return Lanes<T, T>{w + o + s, S}; };
  auto per_scene = [&](int64_t o) { return Lanes<T, T>{w + o + g, G}; };
  Strand<T, T> st;
  st.n = N;
  st.rest = per_strand(off.rest);
  st.mass = per_strand(off.mass);
  st.drag = per_strand(off.drag);
  for (int k = 0; k < 3; ++k) {
    st.stiffness[k] = per_strand(off.stiffness[k]);
    st.rest_length[k] = per_strand(off.rest_length[k]);
  }
  st.integrity = per_strand(off.integrity);
  st.angular = per_strand(off.angular);
  st.segment = per_strand(off.segment);
  int64_t p = args.num_pinned[s];
  p = p < 0 ? 0 : (p > N ? N : p);
  st.pinned = T(p);
  st.pinned_max = int(p);
  st.x = per_scene(off.x);
  st.v = per_scene(off.v);
  st.ghost_rest = per_scene(off.ghost_rest);
  st.sag_offset = per_scene(off.sag_offset);
  st.ext = per_scene(off.ext);
  st.has_ext = args.external_force != nullptr;
  st.a = per_scene(off.a);
  st.b = per_scene(off.b);
  st.force = per_scene(off.force);
  st.ghost = per_scene(off.ghost);
  st.ghost_velocity = per_scene(off.ghost_velocity);
  const Material<T> mat{{args.gravity[0], args.gravity[1], args.gravity[2]}, *args.transition, *args.breaking,
                        *args.soft_ratio};
  const T* scene_poses = poses + (pose_scenes == 1 ? 0 : b) * (cfg.substeps + 1) * kPoseElems;
  if (!adjoint) {
    strand_frame(st, mat, cfg, scene_poses);
    return;
  }
  Adjoint<T, T> adj;
  adj.hist_x = per_scene(off.hist_x);
  adj.hist_v = per_scene(off.hist_v);
  adj.xb = per_scene(off.xb);
  adj.vb = per_scene(off.vb);
  adj.xb_new = per_scene(off.xb_new);
  adj.vb_new = per_scene(off.vb_new);
  adj.lam = per_scene(off.lam);
  adj.ya = per_scene(off.ya);
  adj.yb = per_scene(off.yb);
  adj.wb = per_scene(off.wb);
  adj.vpb = per_scene(off.vpb);
  adj.gb = per_scene(off.gb);
  adj.extb = per_scene(off.extb);
  adj.massb = per_scene(off.massb);
  adj.dragb = per_scene(off.dragb);
  adj.integrityb = per_scene(off.integrityb);
  for (int k = 0; k < 3; ++k) adj.stiffb[k] = per_scene(off.stiffb[k]);
  adj.angularb = per_scene(off.angularb);
  adj.poseb = per_scene(off.poseb);
  adj.sagb = per_scene(off.sagb);
  adj.lawb = per_scene(off.lawb);
  strand_frame_adjoint(st, adj, mat, cfg, scene_poses);
}

} // namespace

int64_t frame_adjoint_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t substeps) {
  return AdjointOffsets(scenes, strands, particles, substeps).total;
}

template <class T>
cudaError_t frame_adjoint_cuda(const FrameArgs<T>& args, const FrameSettings& cfg, const T* poses, int64_t pose_scenes,
                               T* out_x, T* out_v, const AdjointBuffers<T>* adjoint, T* workspace,
                               cudaStream_t stream) {
  const int64_t B = args.scenes, S = args.strands, N = args.particles, M = cfg.substeps, G = B * S;
  if (G <= 0) return cudaSuccess;
  const AdjointOffsets off(B, S, N, M);
  T* w = workspace;

  TransposeBatch<T> in; // (strands, values) -> (values, strands)
  bool ok = in.add(args.rest_positions, w + off.rest, S, 3 * N);
  ok &= in.add(args.mass, w + off.mass, S, N);
  ok &= in.add(args.drag, w + off.drag, S, N);
  for (int k = 0; k < 3; ++k) {
    ok &= in.add(args.stiffness[k], w + off.stiffness[k], S, N - 1 - k);
    ok &= in.add(args.rest_length[k], w + off.rest_length[k], S, N - 1 - k);
  }
  if (cfg.integrity_model != kIntegrityNone) ok &= in.add(args.integrity, w + off.integrity, S, N);
  if (cfg.angular) ok &= in.add(args.angular, w + off.angular, S, N - 1);
  const bool nonhookean = cfg.integrity_model == kIntegrityNonHookean;
  if (nonhookean) ok &= in.add(args.segment_length, w + off.segment, S, N);
  ok &= in.add(args.x, w + off.x, G, 3 * N);
  ok &= in.add(args.v, w + off.v, G, 3 * N);
  ok &= in.add(args.ghost_rest, w + off.ghost_rest, G, 3 * N);
  if (nonhookean) ok &= in.add(args.sag_offset, w + off.sag_offset, G, 3 * N);
  if (args.external_force != nullptr) ok &= in.add(args.external_force, w + off.ext, G, 3 * N);
  if (adjoint != nullptr) {
    ok &= in.add(adjoint->xb_in, w + off.xb, G, 3 * N);
    ok &= in.add(adjoint->vb_in, w + off.vb, G, 3 * N);
  }
  if (!ok) return cudaErrorInvalidConfiguration;
  launch_transpose(in, stream);

  const int64_t grid = (G + kAdjointThreads - 1) / kAdjointThreads;
  if (grid > 0x7fffffffLL) return cudaErrorInvalidConfiguration;
  adjoint_kernel<T><<<unsigned(grid), kAdjointThreads, 0, stream>>>(args, cfg, poses, pose_scenes, w, off,
                                                                    adjoint != nullptr);

  TransposeBatch<T> back; // (values, strands) -> (strands, values)
  if (adjoint == nullptr) {
    ok = back.add(w + off.x, out_x, 3 * N, G);
    ok &= back.add(w + off.v, out_v, 3 * N, G);
  } else {
    ok = back.add(w + off.xb, adjoint->xb, 3 * N, G);
    ok &= back.add(w + off.vb, adjoint->vb, 3 * N, G);
    ok &= back.add(w + off.gb, adjoint->gb, 3 * N, G);
    if (adjoint->extb != nullptr) ok &= back.add(w + off.extb, adjoint->extb, 3 * N, G);
    ok &= back.add(w + off.massb, adjoint->massb, N, G);
    ok &= back.add(w + off.dragb, adjoint->dragb, N, G);
    for (int k = 0; k < 3; ++k) ok &= back.add(w + off.stiffb[k], adjoint->stiffb[k], N - 1 - k, G);
    ok &= back.add(w + off.integrityb, adjoint->integrityb, N, G);
    ok &= back.add(w + off.angularb, adjoint->angularb, N - 1, G);
    ok &= back.add(w + off.poseb, adjoint->poseb, int64_t(kPoseElems) * (M + 1), G);
    ok &= back.add(w + off.sagb, adjoint->sagb, 3 * N, G);
    ok &= back.add(w + off.lawb, adjoint->lawb, 3, G);
  }
  if (!ok) return cudaErrorInvalidConfiguration;
  launch_transpose(back, stream);
  return cudaGetLastError();
}

template cudaError_t frame_adjoint_cuda<float>(const FrameArgs<float>&, const FrameSettings&, const float*, int64_t,
                                               float*, float*, const AdjointBuffers<float>*, float*, cudaStream_t);
template cudaError_t frame_adjoint_cuda<double>(const FrameArgs<double>&, const FrameSettings&, const double*, int64_t,
                                                double*, double*, const AdjointBuffers<double>*, double*,
                                                cudaStream_t);

} // namespace frame
} // namespace ams_torch
