// epona/cuda/runtime/check.hpp — error checking for the CUDA runtime and cuBLASLt: every call and
// every kernel launch goes through these macros, which throw epona::Error naming the
// expression, file, line and the library's own error string (never abort, never ignore).
#pragma once

#include <cublasLt.h>
#include <cuda_runtime.h>

#include "epona/core/error.hpp"

namespace epona::cuda::detail {

inline void check_cuda(cudaError_t status, const char* expr, const char* file, int line) {
  if (status == cudaSuccess) return;
  fail("CUDA error ", cudaGetErrorName(status), " (", cudaGetErrorString(status), ") in ", expr, " at ", file,
       ":", line);
}

inline void check_cublas(cublasStatus_t status, const char* expr, const char* file, int line) {
  if (status == CUBLAS_STATUS_SUCCESS) return;
  fail("cuBLAS error ", cublasLtGetStatusName(status), " (", cublasLtGetStatusString(status), ") in ", expr,
       " at ", file, ":", line);
}

}  // namespace epona::cuda::detail

// EPONA_CUDA_CHECK(cudaMalloc(...)): throws epona::Error on any status but cudaSuccess.
#define EPONA_CUDA_CHECK(expr) ::epona::cuda::detail::check_cuda((expr), #expr, __FILE__, __LINE__)
// EPONA_CUBLAS_CHECK(cublasLtMatmul(...)): the same for cuBLAS / cuBLASLt statuses.
#define EPONA_CUBLAS_CHECK(expr) ::epona::cuda::detail::check_cublas((expr), #expr, __FILE__, __LINE__)
// After every kernel launch: launch-configuration errors surface here, at the launch site.
#define EPONA_CUDA_CHECK_LAUNCH() \
  ::epona::cuda::detail::check_cuda(cudaGetLastError(), "kernel launch", __FILE__, __LINE__)

namespace epona::cuda::detail {

// Whether `stream` is being captured into a graph: work queued on it is recorded, not run, so
// nothing can be timed, filled once or read back from the host meanwhile.
inline bool capturing(cudaStream_t stream) {
  cudaStreamCaptureStatus status = cudaStreamCaptureStatusNone;
  EPONA_CUDA_CHECK(cudaStreamIsCapturing(stream, &status));
  return status != cudaStreamCaptureStatusNone;
}

}  // namespace epona::cuda::detail
