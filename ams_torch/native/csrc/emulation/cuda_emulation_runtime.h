// Host emulation of the CUDA runtime API subset used by ams_torch's kernels and their torch
// bindings: the types (dim3, cudaError_t, cudaStream_t, cudaDeviceProp), the error functions,
// memset/memcpy, device queries. Included by the shim headers of emulation/include/ in place of
// <cuda_runtime_api.h> and <cuda_runtime.h>, so that a .cu file and its binding compile as host
// C++ against the CPU torch (ams_torch/native/emulation.py builds them; the tests run them).
//
// "Device" memory is host memory: a pointer from a CPU tensor is used as it is.
// The emulated device (one) is described by the environment, read at each query:
//   AMS_TORCH_EMU_SMS   multiprocessor count (default 132, an H100 SXM)
//   AMS_TORCH_EMU_CC    compute capability "major.minor" (default "9.0")
// No device-side code here: cuda_emulation.h adds the launch, the thread indices, shared memory,
// __syncthreads, warp collectives and atomics.
#pragma once

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <mutex>
#include <string>
#include <unordered_map>

#define AMS_TORCH_CUDA_EMULATION 1

#ifndef CUDART_VERSION
#define CUDART_VERSION 13000
#endif

struct dim3 {
  unsigned int x, y, z;
  constexpr dim3(unsigned int vx = 1, unsigned int vy = 1, unsigned int vz = 1) : x(vx), y(vy), z(vz) {}
};

struct uint3 {
  unsigned int x, y, z;
};

enum cudaError_t {
  cudaSuccess = 0,
  cudaErrorInvalidValue = 1,
  cudaErrorMemoryAllocation = 2,
  cudaErrorInvalidConfiguration = 9,
  cudaErrorInvalidDevice = 101,
  cudaErrorLaunchOutOfResources = 701,
  cudaErrorIllegalInstruction = 715,
  cudaErrorLaunchFailure = 719,
  cudaErrorNotSupported = 801,
  cudaErrorUnknown = 999,
};
typedef cudaError_t cudaError;

struct CUstream_st;
typedef CUstream_st* cudaStream_t;

enum cudaMemcpyKind {
  cudaMemcpyHostToHost = 0,
  cudaMemcpyHostToDevice = 1,
  cudaMemcpyDeviceToHost = 2,
  cudaMemcpyDeviceToDevice = 3,
  cudaMemcpyDefault = 4,
};

enum cudaDeviceAttr {
  cudaDevAttrMaxThreadsPerBlock = 1,
  cudaDevAttrMaxBlockDimX = 2,
  cudaDevAttrMaxBlockDimY = 3,
  cudaDevAttrMaxBlockDimZ = 4,
  cudaDevAttrMaxGridDimX = 5,
  cudaDevAttrMaxGridDimY = 6,
  cudaDevAttrMaxGridDimZ = 7,
  cudaDevAttrMaxSharedMemoryPerBlock = 8,
  cudaDevAttrWarpSize = 10,
  cudaDevAttrMaxRegistersPerBlock = 12,
  cudaDevAttrMultiProcessorCount = 16,
  cudaDevAttrComputeCapabilityMajor = 75,
  cudaDevAttrComputeCapabilityMinor = 76,
  cudaDevAttrMaxSharedMemoryPerBlockOptin = 97,
};

enum cudaStreamCaptureStatus {
  cudaStreamCaptureStatusNone = 0,
  cudaStreamCaptureStatusActive = 1,
  cudaStreamCaptureStatusInvalidated = 2,
};

struct cudaDeviceProp {
  char name[256];
  int major, minor;
  int multiProcessorCount;
  int maxThreadsPerBlock;
  int maxThreadsDim[3];
  int maxGridSize[3];
  size_t sharedMemPerBlock;
  size_t sharedMemPerBlockOptin;
  int regsPerBlock;
  int warpSize;
};

namespace ams_emu {

// The limits a launch is checked against (those of every GPU since Volta).
constexpr unsigned kMaxThreadsPerBlock = 1024;
constexpr unsigned kMaxBlockDim[3] = {1024, 1024, 64};
constexpr unsigned long long kMaxGridDim[3] = {2147483647ull, 65535ull, 65535ull};
constexpr size_t kMaxSharedPerBlock = 48 * 1024;        // without cudaFuncSetAttribute opt-in
constexpr size_t kMaxSharedPerBlockOptin = 227 * 1024;  // sm_90
constexpr int kWarpSize = 32;

inline long env_long(const char* name, long fallback) {
  const char* s = getenv(name);
  if (s == nullptr || *s == '\0') return fallback;
  char* end = nullptr;
  const long v = strtol(s, &end, 10);
  return (end != s && v > 0) ? v : fallback;
}

inline int multiprocessors() { return int(env_long("AMS_TORCH_EMU_SMS", 132)); }

inline void compute_capability(int* major, int* minor) {
  *major = 9;
  *minor = 0;
  const char* s = getenv("AMS_TORCH_EMU_CC");
  if (s != nullptr && *s != '\0') {
    int a = 0, b = 0;
    if (sscanf(s, "%d.%d", &a, &b) >= 1 && a > 0) {
      *major = a;
      *minor = b;
    }
  }
}

// The last error of this host thread (cudaGetLastError resets it), with a detail message.
struct LastError {
  cudaError_t code = cudaSuccess;
  std::string detail;
};
inline thread_local LastError t_last_error;
inline thread_local std::string t_error_text;

inline void set_error(cudaError_t code, const std::string& detail) {
  if (code == cudaSuccess) return;
  t_last_error.code = code;
  t_last_error.detail = detail;
}

inline const char* error_name(cudaError_t e) {
  switch (e) {
    case cudaSuccess: return "no error";
    case cudaErrorInvalidValue: return "invalid argument";
    case cudaErrorMemoryAllocation: return "out of memory";
    case cudaErrorInvalidConfiguration: return "invalid configuration argument";
    case cudaErrorInvalidDevice: return "invalid device ordinal";
    case cudaErrorLaunchOutOfResources: return "too many resources requested for launch";
    case cudaErrorIllegalInstruction: return "an illegal instruction was encountered";
    case cudaErrorLaunchFailure: return "unspecified launch failure";
    case cudaErrorNotSupported: return "operation not supported";
    default: return "unknown error";
  }
}

} // namespace ams_emu

inline cudaError_t cudaGetLastError() {
  const cudaError_t e = ams_emu::t_last_error.code;
  ams_emu::t_last_error.code = cudaSuccess;
  return e;
}

inline cudaError_t cudaPeekAtLastError() { return ams_emu::t_last_error.code; }

// The generic text, plus the emulator's detail when it reported this error on this thread.
inline const char* cudaGetErrorString(cudaError_t e) {
  ams_emu::t_error_text = std::string(ams_emu::error_name(e));
  if (e != cudaSuccess && !ams_emu::t_last_error.detail.empty())
    ams_emu::t_error_text += " (CUDA emulation: " + ams_emu::t_last_error.detail + ")";
  return ams_emu::t_error_text.c_str();
}

inline const char* cudaGetErrorName(cudaError_t e) { return ams_emu::error_name(e); }

inline cudaError_t cudaGetDevice(int* device) {
  *device = 0;
  return cudaSuccess;
}

inline cudaError_t cudaSetDevice(int device) {
  return device == 0 ? cudaSuccess : cudaErrorInvalidDevice;
}

inline cudaError_t cudaGetDeviceCount(int* count) {
  *count = 1;
  return cudaSuccess;
}

inline cudaError_t cudaDeviceGetAttribute(int* value, cudaDeviceAttr attr, int device) {
  if (device != 0) return cudaErrorInvalidDevice;
  int major = 0, minor = 0;
  ams_emu::compute_capability(&major, &minor);
  switch (attr) {
    case cudaDevAttrMaxThreadsPerBlock: *value = int(ams_emu::kMaxThreadsPerBlock); break;
    case cudaDevAttrMaxBlockDimX: *value = int(ams_emu::kMaxBlockDim[0]); break;
    case cudaDevAttrMaxBlockDimY: *value = int(ams_emu::kMaxBlockDim[1]); break;
    case cudaDevAttrMaxBlockDimZ: *value = int(ams_emu::kMaxBlockDim[2]); break;
    case cudaDevAttrMaxGridDimX: *value = int(ams_emu::kMaxGridDim[0]); break;
    case cudaDevAttrMaxGridDimY: *value = int(ams_emu::kMaxGridDim[1]); break;
    case cudaDevAttrMaxGridDimZ: *value = int(ams_emu::kMaxGridDim[2]); break;
    case cudaDevAttrMaxSharedMemoryPerBlock: *value = int(ams_emu::kMaxSharedPerBlock); break;
    case cudaDevAttrMaxSharedMemoryPerBlockOptin: *value = int(ams_emu::kMaxSharedPerBlockOptin); break;
    case cudaDevAttrWarpSize: *value = ams_emu::kWarpSize; break;
    case cudaDevAttrMaxRegistersPerBlock: *value = 65536; break;
    case cudaDevAttrMultiProcessorCount: *value = ams_emu::multiprocessors(); break;
    case cudaDevAttrComputeCapabilityMajor: *value = major; break;
    case cudaDevAttrComputeCapabilityMinor: *value = minor; break;
    default: return cudaErrorInvalidValue;
  }
  return cudaSuccess;
}

inline cudaError_t cudaGetDeviceProperties(cudaDeviceProp* prop, int device) {
  if (device != 0) return cudaErrorInvalidDevice;
  memset(prop, 0, sizeof(*prop));
  strncpy(prop->name, "ams_torch CUDA emulation (host)", sizeof(prop->name) - 1);
  ams_emu::compute_capability(&prop->major, &prop->minor);
  prop->multiProcessorCount = ams_emu::multiprocessors();
  prop->maxThreadsPerBlock = int(ams_emu::kMaxThreadsPerBlock);
  for (int i = 0; i < 3; ++i) {
    prop->maxThreadsDim[i] = int(ams_emu::kMaxBlockDim[i]);
    prop->maxGridSize[i] = int(ams_emu::kMaxGridDim[i]);
  }
  prop->sharedMemPerBlock = ams_emu::kMaxSharedPerBlock;
  prop->sharedMemPerBlockOptin = ams_emu::kMaxSharedPerBlockOptin;
  prop->regsPerBlock = 65536;
  prop->warpSize = ams_emu::kWarpSize;
  return cudaSuccess;
}

// Stream operations run at once (the emulation is synchronous); a null pointer with a non-zero
// size is an invalid value, as on the device.
inline cudaError_t cudaMemsetAsync(void* ptr, int value, size_t bytes, cudaStream_t = nullptr) {
  if (bytes == 0) return cudaSuccess;
  if (ptr == nullptr) return cudaErrorInvalidValue;
  memset(ptr, value, bytes);
  return cudaSuccess;
}

inline cudaError_t cudaMemset(void* ptr, int value, size_t bytes) { return cudaMemsetAsync(ptr, value, bytes); }

inline cudaError_t cudaMemcpyAsync(void* dst, const void* src, size_t bytes, cudaMemcpyKind = cudaMemcpyDefault,
                                   cudaStream_t = nullptr) {
  if (bytes == 0) return cudaSuccess;
  if (dst == nullptr || src == nullptr) return cudaErrorInvalidValue;
  memmove(dst, src, bytes);
  return cudaSuccess;
}

inline cudaError_t cudaMemcpy(void* dst, const void* src, size_t bytes, cudaMemcpyKind kind) {
  return cudaMemcpyAsync(dst, src, bytes, kind);
}

inline cudaError_t cudaStreamSynchronize(cudaStream_t) { return cudaSuccess; }
inline cudaError_t cudaDeviceSynchronize() { return cudaSuccess; }

inline cudaError_t cudaStreamIsCapturing(cudaStream_t, cudaStreamCaptureStatus* status) {
  *status = cudaStreamCaptureStatusNone;
  return cudaSuccess;
}

enum cudaFuncAttribute {
  cudaFuncAttributeMaxDynamicSharedMemorySize = 8,
  cudaFuncAttributePreferredSharedMemoryCarveout = 9,
};

namespace ams_emu {
// Dynamic shared memory a kernel opted in to (cudaFuncSetAttribute), by kernel address.
inline std::mutex g_attr_mutex;
inline std::unordered_map<const void*, size_t> g_dynamic_shared_optin;

inline size_t dynamic_shared_limit(const void* kernel) {
  std::lock_guard<std::mutex> lock(g_attr_mutex);
  const auto it = g_dynamic_shared_optin.find(kernel);
  return it == g_dynamic_shared_optin.end() ? kMaxSharedPerBlock : it->second;
}
} // namespace ams_emu

template <class F>
inline cudaError_t cudaFuncSetAttribute(F* kernel, cudaFuncAttribute attr, int value) {
  if (attr != cudaFuncAttributeMaxDynamicSharedMemorySize) return cudaSuccess;
  if (value < 0 || size_t(value) > ams_emu::kMaxSharedPerBlockOptin) return cudaErrorInvalidValue;
  std::lock_guard<std::mutex> lock(ams_emu::g_attr_mutex);
  ams_emu::g_dynamic_shared_optin[reinterpret_cast<const void*>(kernel)] = size_t(value);
  return cudaSuccess;
}
