// Per-thread scratch for the CPU kernels (banded solve, fused frame, collision stage, grid):
// 64-byte aligned, grown on demand and reused across calls. CPU only (needs torch's TORCH_CHECK).
// One buffer per thread for the whole CPU library (every kernel shares it): a kernel holding its
// scratch must not call code that asks for scratch on the same thread (none does: each op takes
// it once, at its top level or once per worker-thread task).
#pragma once

#include <c10/util/Exception.h>

#include <cstddef>
#include <cstdlib>

namespace ams_torch {

// A buffer of at least ``bytes`` for the calling thread; ``what`` names it in the out-of-memory
// error. The pointer stays valid until the same thread asks for more.
inline void* thread_scratch(size_t bytes, const char* what) {
  struct Buffer {
    void* ptr = nullptr;
    size_t size = 0;
    ~Buffer() { std::free(ptr); }
  };
  thread_local Buffer buf;
  if (buf.size < bytes) {
    std::free(buf.ptr);
    buf.ptr = nullptr;  // a failed allocation must not leave a stale size behind
    buf.size = 0;
    const size_t rounded = (bytes + 63) / 64 * 64;
    buf.ptr = std::aligned_alloc(64, rounded);
    TORCH_CHECK(buf.ptr != nullptr, "ams_torch: out of memory for ", what, " scratch (", rounded, " bytes)");
    buf.size = rounded;
  }
  return buf.ptr;
}

}  // namespace ams_torch
