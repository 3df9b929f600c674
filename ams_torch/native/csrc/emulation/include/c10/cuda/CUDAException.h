// CUDA emulation (ams_torch/native/csrc/emulation): c10's CUDA error checks, for a binding built
// against the CPU torch (the emulated launches report through cudaGetLastError(), as a device does).
#pragma once

#include <c10/util/Exception.h>

#include "cuda_emulation_runtime.h"

#define C10_CUDA_CHECK(EXPR)                                                                       \
  do {                                                                                             \
    const cudaError_t ams_emu_err_ = (EXPR);                                                       \
    TORCH_CHECK(ams_emu_err_ == cudaSuccess, "CUDA error: ", cudaGetErrorString(ams_emu_err_));    \
  } while (0)

#define C10_CUDA_CHECK_WARN(EXPR)                                                                  \
  do {                                                                                             \
    const cudaError_t ams_emu_err_ = (EXPR);                                                       \
    if (ams_emu_err_ != cudaSuccess) TORCH_WARN("CUDA warning: ", cudaGetErrorString(ams_emu_err_)); \
  } while (0)

#define C10_CUDA_KERNEL_LAUNCH_CHECK() C10_CUDA_CHECK(cudaGetLastError())
