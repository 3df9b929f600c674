// CUDA emulation (ams_torch/native/csrc/emulation): ATen's CUDA context (device properties of the
// emulated device, streams), for a binding built against the CPU torch.
#pragma once

#include "c10/cuda/CUDAException.h"
#include "c10/cuda/CUDAFunctions.h"
#include "c10/cuda/CUDAGuard.h"
#include "c10/cuda/CUDAStream.h"

namespace at {
namespace cuda {

using c10::cuda::CUDAStream;
using c10::cuda::getCurrentCUDAStream;
using c10::cuda::getDefaultCUDAStream;
using c10::cuda::getStreamFromPool;
using c10::cuda::setCurrentCUDAStream;

inline cudaDeviceProp* getDeviceProperties(c10::DeviceIndex) {
  static thread_local cudaDeviceProp prop;
  cudaGetDeviceProperties(&prop, 0);  // re-read: the emulated device is set by the environment
  return &prop;
}

inline cudaDeviceProp* getCurrentDeviceProperties() { return getDeviceProperties(0); }

inline int warp_size() { return 32; }

} // namespace cuda
} // namespace at
