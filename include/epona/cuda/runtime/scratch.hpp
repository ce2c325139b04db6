// epona/cuda/runtime/scratch.hpp — device tensors for intermediate results, taken from the device's
// stream-ordered memory pool (cudaMallocAsync on the context's stream, cudaFreeAsync on the same
// stream when the last handle goes), so a forward pass that makes hundreds of short-lived maps
// never calls cudaMalloc/cudaFree (which synchronise). Falls back to plain cudaMalloc.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <mutex>

#include "epona/core/tensor.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/memory.hpp"

namespace epona::cuda {

namespace scratch_detail {

// The device's default pool, set once to keep freed memory for reuse (its default release
// threshold of 0 returns it to the driver at every synchronisation); null when the device has
// no memory pools (then scratch tensors are plain allocations).
inline cudaMemPool_t pool_of(int device) {
  static std::mutex m;
  static cudaMemPool_t pools[kMaxDevices] = {};
  static bool checked[kMaxDevices] = {};
  EPONA_CHECK(device >= 0 && device < kMaxDevices, "scratch memory: device ", device, " out of range");
  std::lock_guard<std::mutex> lock(m);
  if (!checked[device]) {
    checked[device] = true;
    int supported = 0;
    EPONA_CUDA_CHECK(cudaDeviceGetAttribute(&supported, cudaDevAttrMemoryPoolsSupported, device));
    if (supported) {
      EPONA_CUDA_CHECK(cudaDeviceGetDefaultMemPool(&pools[device], device));
      std::uint64_t keep = std::numeric_limits<std::uint64_t>::max();
      EPONA_CUDA_CHECK(cudaMemPoolSetAttribute(pools[device], cudaMemPoolAttrReleaseThreshold, &keep));
    }
  }
  return pools[device];
}

template <class T>
void maybe_poison(Context& ctx, Tensor<T, Cuda>& t) {
  if (ctx.policy().poison_new_buffers && t.numel())
    EPONA_CUDA_CHECK(cudaMemsetAsync(t.data(), 0xFF, t.nbytes(), ctx.stream()));
}

}  // namespace scratch_detail

// Tests set ctx.policy().poison_new_buffers: every scratch and result tensor is filled with 0xFF
// bytes (NaN in float32 and bf16) when it is handed out, so an element that a kernel fails to
// write shows as NaN, even in reused memory.

// A device tensor of `shape` whose memory comes from the pool in the order of ctx's stream.
// It must not outlive ctx (its release is queued on ctx's stream). Results handed to callers
// are ordinary Tensor<T, Cuda> allocations instead.
template <class T>
Tensor<T, Cuda> scratch_tensor(Context& ctx, Shape shape, T* = nullptr) {
  if (!scratch_detail::pool_of(ctx.info().device)) {
    Tensor<T, Cuda> t(std::move(shape));
    scratch_detail::maybe_poison(ctx, t);
    return t;
  }
  const std::size_t bytes = std::max<std::size_t>(1, static_cast<std::size_t>(shape_numel(shape)) * sizeof(T));
  void* p = nullptr;
  const cudaError_t status = cudaMallocAsync(&p, bytes, ctx.stream());
  if (status != cudaSuccess) {
    (void)cudaGetLastError();
    fail("out of device memory: cannot allocate ", bytes, " bytes of scratch for ", shape_str(shape), " (",
         cudaGetErrorString(status), ")");
  }
  cudaStream_t stream = ctx.stream();
  // A deleter must not throw; a failing free at shutdown has nothing left to report to.
  std::shared_ptr<void> owner(p, [stream](void* q) { cudaFreeAsync(q, stream); });
  auto t = Tensor<T, Cuda>::view(static_cast<T*>(p), std::move(shape), std::move(owner));
  scratch_detail::maybe_poison(ctx, t);
  return t;
}

// A tensor for a result handed to the caller: an ordinary allocation (may outlive ctx).
template <class T>
Tensor<T, Cuda> result_tensor(Context& ctx, Shape shape, T* = nullptr) {
  Tensor<T, Cuda> t(std::move(shape));
  scratch_detail::maybe_poison(ctx, t);
  return t;
}

// Bytes of the pool in use now / at most since the last reset (0 without memory pools).
struct ScratchUsage {
  std::uint64_t used = 0, peak = 0;
};
inline ScratchUsage scratch_usage(const Context& ctx) {
  ScratchUsage u;
  if (cudaMemPool_t pool = scratch_detail::pool_of(ctx.info().device)) {
    EPONA_CUDA_CHECK(cudaMemPoolGetAttribute(pool, cudaMemPoolAttrUsedMemCurrent, &u.used));
    EPONA_CUDA_CHECK(cudaMemPoolGetAttribute(pool, cudaMemPoolAttrUsedMemHigh, &u.peak));
  }
  return u;
}
inline void reset_scratch_peak(const Context& ctx) {
  if (cudaMemPool_t pool = scratch_detail::pool_of(ctx.info().device)) {
    std::uint64_t zero = 0;
    EPONA_CUDA_CHECK(cudaMemPoolSetAttribute(pool, cudaMemPoolAttrUsedMemHigh, &zero));
  }
  std::uint64_t zero = 0;
  EPONA_CUDA_CHECK(cudaDeviceSetGraphMemAttribute(ctx.info().device, cudaGraphMemAttrUsedMemHigh, &zero));
}
// Bytes of graph-owned memory (scratch allocated inside recorded graphs) at most since the last reset.
inline std::uint64_t graph_memory_peak(const Context& ctx) {
  std::uint64_t v = 0;
  EPONA_CUDA_CHECK(cudaDeviceGetGraphMemAttribute(ctx.info().device, cudaGraphMemAttrUsedMemHigh, &v));
  return v;
}

}  // namespace epona::cuda
