// The colliders' per-scene table of the CUDA collision kernels (collide_cuda.cu and its adjoint,
// collide_adjoint_cuda.cu): B × C prepared colliders at the start of the workspace, prepared once per
// call by one thread per (scene, collider), then read by every thread of a scene (broadcast).
// Included by .cu files only (an unnamed namespace: each kernel file keeps its own copy).
#pragma once

#include <stdint.h>

#include "collide/collide.h"

namespace ams_torch {
namespace collide {
namespace {

constexpr int kPrepareThreads = 64;

// Elements of T the table takes, rounded up so that what follows is 256-byte aligned.
int64_t table_elems(int64_t scenes, int64_t colliders, int64_t elem_bytes, int64_t prepared_bytes) {
  const int64_t bytes = scenes * colliders * prepared_bytes;
  return ((bytes + 255) / 256 * 256) / elem_bytes;
}

template <class T>
__global__ void prepare_kernel(const CollideArgs<T> args, Prepared<T>* table) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= args.scenes * args.count) return;
  prepare_collider(args.colliders[i % args.count], i / args.count, table[i]);
}

// Launch the preparation of the B × C table at `table` on `stream`.
template <class T>
void launch_prepare(const CollideArgs<T>& args, Prepared<T>* table, cudaStream_t stream) {
  const int64_t n = args.scenes * args.count;
  if (n > 0) prepare_kernel<T><<<unsigned((n + kPrepareThreads - 1) / kPrepareThreads), kPrepareThreads, 0, stream>>>(
      args, table);
}

} // namespace
} // namespace collide
} // namespace ams_torch
