// epona/cuda/device.cuh — small device primitives shared by the CUDA kernels: float <->
// storage-type conversion (bf16 storage, float32 arithmetic), PyTorch's type promotion for
// mixed-precision element-wise ops, warp/block reductions and the launch-size helper.
#pragma once

#include <cuda_bf16.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/cuda/check.hpp"

namespace epona::cuda {

static_assert(sizeof(bf16) == sizeof(__nv_bfloat16) && alignof(bf16) == alignof(__nv_bfloat16),
              "epona::bf16 must be layout-compatible with __nv_bfloat16");

template <class T>
inline constexpr bool is_device_float = std::is_same_v<T, float> || std::is_same_v<T, bf16>;

namespace detail {

// Loads/stores in float32; bf16 rounds to nearest even like epona::bf16 and PyTorch.
__device__ __forceinline__ float to_f32(float v) { return v; }
__device__ __forceinline__ float to_f32(bf16 v) {
  return __uint_as_float(static_cast<unsigned>(v.bits) << 16);
}
template <class T> __device__ __forceinline__ T from_f32(float v);
template <> __device__ __forceinline__ float from_f32<float>(float v) { return v; }
template <> __device__ __forceinline__ bf16 from_f32<bf16>(float v) {
  bf16 r;
  r.bits = __bfloat16_as_ushort(__float2bfloat16_rn(v));
  return r;
}
// Rounds a float32 value to what storage type T would hold, keeping it in float32.
template <class T> __device__ __forceinline__ float round_to(float v) { return to_f32(from_f32<T>(v)); }

// The result type of a binary op of PyTorch tensors of types A and B (bf16 only if both are).
template <class A, class B>
using promote_t = std::conditional_t<std::is_same_v<A, bf16> && std::is_same_v<B, bf16>, bf16, float>;

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// Sum over all threads of the block (blockDim.x a multiple of 32, at most 1024); every
// thread gets the result. `scratch` is 32 floats of shared memory, free again on return.
__device__ __forceinline__ float block_sum(float v, float* scratch) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  v = warp_sum(v);
  if (lane == 0) scratch[warp] = v;
  __syncthreads();
  float total = lane < warps ? scratch[lane] : 0.f;
  total = warp_sum(total);
  __syncthreads();  // scratch may be reused by the caller's next reduction
  return total;
}

// Blocks for a grid-stride loop over n elements: enough to fill the device, no more.
inline unsigned grid_for(std::int64_t n, int threads) {
  const std::int64_t blocks = (n + threads - 1) / threads;
  return static_cast<unsigned>(std::clamp<std::int64_t>(blocks, 1, 65535L * 8));
}

}  // namespace detail
}  // namespace epona::cuda
