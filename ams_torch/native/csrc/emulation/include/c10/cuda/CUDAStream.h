// CUDA emulation (ams_torch/native/csrc/emulation): c10's CUDA stream, for a binding built against
// the CPU torch. Every stream is the null stream; work runs at once on the calling thread.
#pragma once

#include <c10/core/Device.h>

#include "cuda_emulation_runtime.h"

namespace c10 {
namespace cuda {

class CUDAStream {
 public:
  explicit CUDAStream(c10::DeviceIndex index = -1) : index_(index) {}
  cudaStream_t stream() const { return nullptr; }
  operator cudaStream_t() const { return stream(); }
  c10::DeviceIndex device_index() const { return index_; }
  int64_t id() const { return 0; }
  bool query() const { return true; }
  void synchronize() const {}
  bool operator==(const CUDAStream& other) const { return index_ == other.index_; }
  bool operator!=(const CUDAStream& other) const { return !(*this == other); }

 private:
  c10::DeviceIndex index_;
};

inline CUDAStream getCurrentCUDAStream(c10::DeviceIndex index = -1) { return CUDAStream(index); }
inline CUDAStream getDefaultCUDAStream(c10::DeviceIndex index = -1) { return CUDAStream(index); }
inline CUDAStream getStreamFromPool(bool = false, c10::DeviceIndex index = -1) { return CUDAStream(index); }
inline void setCurrentCUDAStream(CUDAStream) {}

} // namespace cuda
} // namespace c10
