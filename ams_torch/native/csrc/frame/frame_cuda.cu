// CUDA kernel of the fused frame of strand dynamics. One thread per (scene, strand) runs the
// shared per-strand routine of frame.h (the CPU kernel runs the same code on SIMD lanes).
//
// Layout choice: the inputs are transposed once per call into a strand-interleaved copy in the
// workspace (value e of strand s at e · strands + s) by one batched tiled transpose, and the two
// results are transposed back at the end. The frame reads every input M times (and the matrix,
// right-hand side and state arrays many times per substep), so with torch's (strand, value)
// layout each warp-wide access would touch 32 cache lines; interleaved, the 32 threads of a warp
// read and write 32 consecutive values at every step (coalesced), for the price of one extra read
// and write of the inputs. The matrix lives only in the workspace (assembled, factored and solved
// in place). Per-strand data (rest shape, coefficients) is interleaved once per strand and shared
// by the scenes; per-scene data per (scene, strand). No torch headers: see frame_cuda.h.
// The frame's end (finish.h) is a separate kernel, one thread per particle.
#include <cuda_runtime.h>

#include <stdint.h>

#include "frame/frame.h"
#include "frame/frame_cuda.h"
#include "common/launch_cuda.cuh"
#include "common/transpose_cuda.cuh"

namespace ams_torch {
namespace frame {
namespace {

constexpr int kFrameThreads = 128; // most strands per frame block (fewer for small scenes: strand_block_threads)
constexpr int kPoseThreads = 64;

// Workspace arrays (offsets in elements of T; model arrays hold count × strands values,
// scene arrays count × scenes × strands).
struct Offsets {
  int64_t poses, rest, mass, drag, stiffness[3], rest_length[3], integrity, angular, segment;
  int64_t x, v, ghost_rest, sag_offset, ext, a, b, force, ghost, ghost_velocity, total;
  Offsets(int64_t B, int64_t S, int64_t N, int64_t M) {
    const int64_t G = B * S;
    int64_t o = 0;
    auto take = [&o](int64_t count) {
      const int64_t at = o;
      o += count;
      return at;
    };
    poses = take(B * (M + 1) * kPoseElems);
    rest = take(3 * N * S);
    mass = take(N * S);
    drag = take(N * S);
    for (int k = 0; k < 3; ++k) stiffness[k] = take((N - 1 - k) * S);
    for (int k = 0; k < 3; ++k) rest_length[k] = take((N - 1 - k) * S);
    integrity = take(N * S);
    angular = take((N - 1) * S);
    segment = take(N * S);
    x = take(3 * N * G);
    v = take(3 * N * G);
    ghost_rest = take(3 * N * G);
    sag_offset = take(3 * N * G);
    ext = take(3 * N * G);
    a = take(banded::kRowElems * N * G);
    b = take(3 * N * G);
    force = take(3 * N * G);
    ghost = take(3 * N * G);
    ghost_velocity = take(3 * N * G);
    total = o;
  }
};

template <class T>
struct Workspace {
  T* poses;
  T *rest, *mass, *drag, *stiffness[3], *rest_length[3], *integrity, *angular, *segment;
  T *x, *v, *ghost_rest, *sag_offset, *ext, *a, *b, *force, *ghost, *ghost_velocity;
};

template <class T>
Workspace<T> workspace_views(T* w, const Offsets& o) {
  Workspace<T> ws;
  ws.poses = w + o.poses;
  ws.rest = w + o.rest;
  ws.mass = w + o.mass;
  ws.drag = w + o.drag;
  for (int k = 0; k < 3; ++k) {
    ws.stiffness[k] = w + o.stiffness[k];
    ws.rest_length[k] = w + o.rest_length[k];
  }
  ws.integrity = w + o.integrity;
  ws.angular = w + o.angular;
  ws.segment = w + o.segment;
  ws.x = w + o.x;
  ws.v = w + o.v;
  ws.ghost_rest = w + o.ghost_rest;
  ws.sag_offset = w + o.sag_offset;
  ws.ext = w + o.ext;
  ws.a = w + o.a;
  ws.b = w + o.b;
  ws.force = w + o.force;
  ws.ghost = w + o.ghost;
  ws.ghost_velocity = w + o.ghost_velocity;
  return ws;
}

template <class T>
__global__ void pose_kernel(const FrameArgs<T> args, int substeps, bool hermite, double dt, T* out) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= args.scenes * (substeps + 1)) return;
  substep_pose(args, i / (substeps + 1), int(i % (substeps + 1)), substeps, hermite, dt, out + i * kPoseElems);
}

// Substep contact: collider c of scene b at substep k, prepared once per call into
// table[(b · M + k) · C + c] (read by every thread of the scene).
template <class T>
__global__ void contact_prepare_kernel(const ContactArgs<T> contact, int64_t scenes, int substeps,
                                       collide::Prepared<T>* table) {
  const int64_t C = contact.count;
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= scenes * substeps * C) return;
  const int64_t c = i % C, k = (i / C) % substeps, b = i / (C * substeps);
  collide::prepare_collider(contact_collider(contact, int(c), int(k)), b, table[i]);
}

template <class T>
__global__ void __launch_bounds__(kFrameThreads) frame_kernel(const FrameArgs<T> args, const FrameSettings cfg,
                                                                const Workspace<T> ws, int64_t assemble_substep,
                                                                const collide::Prepared<T>* contact,
                                                                int contact_count) {
  const int64_t S = args.strands, N = args.particles, G = args.scenes * S;
  const int64_t g = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (g >= G) return;
  const int64_t b = g / S, s = g % S;
  auto per_strand = [&](T* base) { return Lanes<T, T>{base + s, S}; };
  auto per_scene = [&](T* base) { return Lanes<T, T>{base + g, G}; };
  Strand<T, T> st;
  st.n = N;
  st.rest = per_strand(ws.rest);
  st.mass = per_strand(ws.mass);
  st.drag = per_strand(ws.drag);
  for (int k = 0; k < 3; ++k) {
    st.stiffness[k] = per_strand(ws.stiffness[k]);
    st.rest_length[k] = per_strand(ws.rest_length[k]);
  }
  st.integrity = per_strand(ws.integrity);
  st.angular = per_strand(ws.angular);
  st.segment = per_strand(ws.segment);
  int64_t p = args.num_pinned[s];
  p = p < 0 ? 0 : (p > N ? N : p);
  st.pinned = T(p);
  st.pinned_max = int(p);
  st.x = per_scene(ws.x);
  st.v = per_scene(ws.v);
  st.ghost_rest = per_scene(ws.ghost_rest);
  st.sag_offset = per_scene(ws.sag_offset);
  st.ext = per_scene(ws.ext);
  st.has_ext = args.external_force != nullptr;
  st.a = per_scene(ws.a);
  st.b = per_scene(ws.b);
  st.force = per_scene(ws.force);
  st.ghost = per_scene(ws.ghost);
  st.ghost_velocity = per_scene(ws.ghost_velocity);
  const Material<T> mat{{args.gravity[0], args.gravity[1], args.gravity[2]}, *args.transition, *args.breaking,
                        *args.soft_ratio};
  const T* poses = ws.poses + b * (cfg.substeps + 1) * kPoseElems;
  if (assemble_substep >= 0) {
    const T* pa = poses + assemble_substep * kPoseElems;
    assemble(st, mat, cfg, pa, pa + kPoseElems);
    mirror_blocks(st.a, N);
  } else {
    strand_frame(st, mat, cfg, poses, contact != nullptr ? contact + b * cfg.substeps * contact_count : nullptr,
                 contact_count);
  }
}

template <class T>
__global__ void finish_kernel(const FinishArgs<T> args, int64_t count) {
  const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p < count) finish_particle(args, p);
}

} // namespace

template <class T>
cudaError_t finish_cuda(const FinishArgs<T>& args, cudaStream_t stream) {
  const int64_t count = args.scenes * args.strands * args.particles;
  if (count <= 0) return cudaSuccess;
  constexpr int threads = 256;
  const int64_t blocks = (count + threads - 1) / threads;
  if (blocks > 0x7fffffffLL) return cudaErrorInvalidConfiguration;
  finish_kernel<T><<<unsigned(blocks), threads, 0, stream>>>(args, count);
  return cudaGetLastError();
}

template cudaError_t finish_cuda<float>(const FinishArgs<float>&, cudaStream_t);
template cudaError_t finish_cuda<double>(const FinishArgs<double>&, cudaStream_t);

int64_t frame_cuda_workspace_elems(int64_t scenes, int64_t strands, int64_t particles, int64_t substeps) {
  return Offsets(scenes, strands, particles, substeps).total;
}

namespace {

// The launches of frame_cuda (contact: the prepared colliders of substep contact, or none).
template <class T>
cudaError_t launch_frame(const FrameArgs<T>& args, const FrameSettings& cfg, int64_t assemble_substep, T* out0,
                         T* out1, T* workspace, const collide::Prepared<T>* contact, int contact_count,
                         cudaStream_t stream) {
  const int64_t B = args.scenes, S = args.strands, N = args.particles, M = cfg.substeps, G = B * S;
  if (G <= 0) return cudaSuccess;
  const Offsets off(B, S, N, M);
  const Workspace<T> ws = workspace_views(workspace, off);

  const int64_t pose_count = B * (M + 1);
  pose_kernel<T><<<unsigned((pose_count + kPoseThreads - 1) / kPoseThreads), kPoseThreads, 0, stream>>>(
      args, int(M), cfg.hermite, cfg.dt, ws.poses);

  const bool nonhookean = cfg.integrity_model == kIntegrityNonHookean;
  TransposeBatch<T> in; // (strands, values) -> (values, strands)
  in.add(args.rest_positions, ws.rest, S, 3 * N);
  in.add(args.mass, ws.mass, S, N);
  in.add(args.drag, ws.drag, S, N);
  for (int k = 0; k < 3; ++k) {
    in.add(args.stiffness[k], ws.stiffness[k], S, N - 1 - k);
    in.add(args.rest_length[k], ws.rest_length[k], S, N - 1 - k);
  }
  if (cfg.integrity_model != kIntegrityNone) in.add(args.integrity, ws.integrity, S, N);
  if (cfg.angular) in.add(args.angular, ws.angular, S, N - 1);
  if (nonhookean) in.add(args.segment_length, ws.segment, S, N);
  in.add(args.x, ws.x, G, 3 * N);
  in.add(args.v, ws.v, G, 3 * N);
  in.add(args.ghost_rest, ws.ghost_rest, G, 3 * N);
  if (nonhookean) in.add(args.sag_offset, ws.sag_offset, G, 3 * N);
  if (args.external_force != nullptr) in.add(args.external_force, ws.ext, G, 3 * N);
  launch_transpose(in, stream);

  const int threads = cuda::strand_block_threads(G, kFrameThreads);
  const int64_t grid = (G + threads - 1) / threads;
  if (grid > 0x7fffffffLL) return cudaErrorInvalidConfiguration;
  frame_kernel<T><<<unsigned(grid), threads, 0, stream>>>(args, cfg, ws, assemble_substep, contact, contact_count);

  TransposeBatch<T> back; // (values, strands) -> (strands, values)
  if (assemble_substep >= 0) {
    back.add(ws.a, out0, banded::kRowElems * N, G);
    back.add(ws.b, out1, 3 * N, G);
  } else {
    back.add(ws.x, out0, 3 * N, G);
    back.add(ws.v, out1, 3 * N, G);
  }
  launch_transpose(back, stream);
  return cudaGetLastError();
}

} // namespace

template <class T>
cudaError_t frame_cuda(const FrameArgs<T>& args, const FrameSettings& cfg, int64_t assemble_substep, T* out0, T* out1,
                       T* workspace, cudaStream_t stream) {
  return launch_frame(args, cfg, assemble_substep, out0, out1, workspace, (const collide::Prepared<T>*)nullptr, 0,
                      stream);
}

int64_t frame_contact_table_bytes(int64_t scenes, int64_t substeps, int64_t colliders, int64_t elem_bytes) {
  const int64_t prepared = elem_bytes == 4 ? int64_t(sizeof(collide::Prepared<float>))
                                           : int64_t(sizeof(collide::Prepared<double>));
  return scenes * substeps * colliders * prepared;
}

template <class T>
cudaError_t frame_contact_cuda(const FrameArgs<T>& args, const ContactArgs<T>& contact, const FrameSettings& cfg,
                               T* out0, T* out1, T* workspace, void* table, cudaStream_t stream) {
  const int64_t count = args.scenes * cfg.substeps * contact.count;
  if (args.scenes * args.strands <= 0) return cudaSuccess;
  auto* prepared = static_cast<collide::Prepared<T>*>(table);
  if (count > 0) {
    contact_prepare_kernel<T><<<unsigned((count + kPoseThreads - 1) / kPoseThreads), kPoseThreads, 0, stream>>>(
        contact, args.scenes, cfg.substeps, prepared);
  }
  return launch_frame(args, cfg, -1, out0, out1, workspace, count > 0 ? prepared : nullptr, contact.count, stream);
}

template cudaError_t frame_contact_cuda<float>(const FrameArgs<float>&, const ContactArgs<float>&,
                                               const FrameSettings&, float*, float*, float*, void*, cudaStream_t);
template cudaError_t frame_contact_cuda<double>(const FrameArgs<double>&, const ContactArgs<double>&,
                                                const FrameSettings&, double*, double*, double*, void*, cudaStream_t);

template cudaError_t frame_cuda<float>(const FrameArgs<float>&, const FrameSettings&, int64_t, float*, float*, float*,
                                       cudaStream_t);
template cudaError_t frame_cuda<double>(const FrameArgs<double>&, const FrameSettings&, int64_t, double*, double*,
                                        double*, cudaStream_t);

} // namespace frame
} // namespace ams_torch
