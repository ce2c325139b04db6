// epona/cuda/runtime/device.cuh — small device primitives shared by the CUDA kernels: float <->
// storage-type conversion (bf16 storage, float32 arithmetic), PyTorch's type promotion for
// mixed-precision element-wise ops, warp/block reductions and the launch-size helper.
#pragma once

#include <cuda_bf16.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <mutex>
#include <type_traits>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"

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

// Eight consecutive elements as float32, moved with 16-byte accesses (one for bf16, two for
// float): the memory-bound kernels' unit of work. p must be 16-byte aligned.
constexpr int kPack = 8;
__device__ __forceinline__ void load8(const float* p, float (&v)[kPack]) {
  const float4 a = reinterpret_cast<const float4*>(p)[0], b = reinterpret_cast<const float4*>(p)[1];
  v[0] = a.x, v[1] = a.y, v[2] = a.z, v[3] = a.w, v[4] = b.x, v[5] = b.y, v[6] = b.z, v[7] = b.w;
}
__device__ __forceinline__ void load8(const bf16* p, float (&v)[kPack]) {
  const uint4 raw = *reinterpret_cast<const uint4*>(p);
  const unsigned w[4] = {raw.x, raw.y, raw.z, raw.w};
#pragma unroll
  for (int i = 0; i < 4; ++i) {
    v[2 * i] = __uint_as_float(w[i] << 16);
    v[2 * i + 1] = __uint_as_float(w[i] & 0xffff0000u);
  }
}
__device__ __forceinline__ void store8(float* p, const float (&v)[kPack]) {
  reinterpret_cast<float4*>(p)[0] = make_float4(v[0], v[1], v[2], v[3]);
  reinterpret_cast<float4*>(p)[1] = make_float4(v[4], v[5], v[6], v[7]);
}
__device__ __forceinline__ void store8(bf16* p, const float (&v)[kPack]) {
  unsigned w[4];
#pragma unroll
  for (int i = 0; i < 4; ++i) {
    const __nv_bfloat162 h = __floats2bfloat162_rn(v[2 * i], v[2 * i + 1]);
    w[i] = *reinterpret_cast<const unsigned*>(&h);
  }
  *reinterpret_cast<uint4*>(p) = make_uint4(w[0], w[1], w[2], w[3]);
}

// Four consecutive elements as float32 (one 16-byte float or 8-byte bf16 access; p aligned to
// 4 elements): a lane's share where a warp holds a 128-wide row.
__device__ __forceinline__ void load4(const float* p, float (&v)[4]) {
  const float4 a = *reinterpret_cast<const float4*>(p);
  v[0] = a.x, v[1] = a.y, v[2] = a.z, v[3] = a.w;
}
__device__ __forceinline__ void load4(const bf16* p, float (&v)[4]) {
  const uint2 raw = *reinterpret_cast<const uint2*>(p);
  v[0] = __uint_as_float(raw.x << 16), v[1] = __uint_as_float(raw.x & 0xffff0000u);
  v[2] = __uint_as_float(raw.y << 16), v[3] = __uint_as_float(raw.y & 0xffff0000u);
}
__device__ __forceinline__ void store4(float* p, const float (&v)[4]) {
  *reinterpret_cast<float4*>(p) = make_float4(v[0], v[1], v[2], v[3]);
}
__device__ __forceinline__ void store4(bf16* p, const float (&v)[4]) {
  const __nv_bfloat162 a = __floats2bfloat162_rn(v[0], v[1]), b = __floats2bfloat162_rn(v[2], v[3]);
  *reinterpret_cast<uint2*>(p) = make_uint2(*reinterpret_cast<const unsigned*>(&a), *reinterpret_cast<const unsigned*>(&b));
}

inline bool aligned16(const void* p) { return reinterpret_cast<std::uintptr_t>(p) % 16 == 0; }

// Build markers: one binary may carry device code for several targets, and some kernels exist
// only in some of them (wgmma in sm_90a code, thread-block clusters from sm_90). A marker
// kernel calls mark_build only inside the feature's #if; its static shared memory then tells
// the host (build_marked) whether the code this GPU runs has the feature.
__device__ __forceinline__ void mark_build(int* flag) {
  __shared__ int present[4];
  present[threadIdx.x % 4] = 1;
  __syncthreads();
  if (flag) *flag = present[0];
}
template <class Marker>
bool build_marked(Marker* marker) {
  cudaFuncAttributes attr{};
  if (cudaFuncGetAttributes(&attr, marker) != cudaSuccess) {
    (void)cudaGetLastError();
    return false;
  }
  return attr.sharedSizeBytes > 0;  // reported rounded up to the allocation granularity
}

// Rows of width n, ldp apart, can be walked in 16-byte packs from p (null p counts as fine).
inline bool packable(const void* p, std::int64_t n, std::int64_t ldp) {
  return !p || (aligned16(p) && n % kPack == 0 && ldp % kPack == 0);
}

// Blocks for a grid-stride loop over n elements: enough to fill the device, no more.
inline unsigned grid_for(std::int64_t n, int threads) {
  const std::int64_t blocks = (n + threads - 1) / threads;
  return static_cast<unsigned>(std::clamp<std::int64_t>(blocks, 1, 65535L * 8));
}

// Programmatic dependent launch (sm_90 on). A kernel started by launch_after may be scheduled
// while the kernel before it in the stream is still running, which hides most of the launch
// latency between dependent kernels (the DiT samplers' steps are chains of small kernels). It
// calls wait_for_producer() before touching global memory: that waits until the earlier kernel
// has finished and its writes are visible, then lets the next kernel in the stream be scheduled
// (its blocks wait in their own wait_for_producer until this grid has finished). Without a
// programmatic dependency both instructions return at once. The context's
// policy().programmatic_launch off (EPONA_CUDA_PDL=0) launches plainly.
__device__ __forceinline__ void wait_for_producer() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  asm volatile("griddepcontrol.wait;\n" ::: "memory");
  asm volatile("griddepcontrol.launch_dependents;\n" ::: "memory");
#endif
}
// Index i of n items in the pass order. The large row passes (the MST's warp-per-row LayerNorms
// and QK LayerNorm + RoPE, the bf16 table pass) walk their rows last to first where
// ctx.policy().reversed_passes (EPONA_CUDA_REVERSE_PASSES=0: first to last). The product before
// a pass writes its last rows last, so those are still in L2 when the pass starts, and the
// pass's first rows, written last, are in L2 for the next product. Measured on the H200 (MST,
// medians, docs/gpu-log.md "Session 16"): 0.16–0.3 ms faster, up to 1.1 ms once the board has
// been at its power limit for a while; the DC-AE decode unchanged.
__device__ __forceinline__ std::int64_t pass_index(std::int64_t i, std::int64_t n, bool reverse) {
  return reverse ? n - 1 - i : i;
}
// Whether the current device takes the launch attribute (compute capability 9.0 or newer).
inline bool programmatic_launch_available() {
  int device = 0, major = 0;
  EPONA_CUDA_CHECK(cudaGetDevice(&device));
  EPONA_CUDA_CHECK(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device));
  return major >= 9;
}
// Launches kernel with cfg, its own attributes (at most one, e.g. a cluster shape) plus the
// programmatic-serialisation one where `programmatic` (the context's policy); the kernel must
// begin with wait_for_producer(). launch_after and launch_in_clusters (cluster.cuh) both launch
// through it.
template <class... Params, class... Args>
void launch_programmatic(cudaLaunchConfig_t cfg, bool programmatic, void (*kernel)(Params...), const Args&... args) {
  static const bool available = programmatic_launch_available();
  cudaLaunchAttribute attrs[2]{};
  if (cfg.numAttrs == 1) attrs[0] = cfg.attrs[0];
  attrs[cfg.numAttrs].id = cudaLaunchAttributeProgrammaticStreamSerialization;
  attrs[cfg.numAttrs].val.programmaticStreamSerializationAllowed = 1;
  cfg.attrs = attrs;
  cfg.numAttrs += programmatic && available ? 1 : 0;
  EPONA_CUDA_CHECK(cudaLaunchKernelEx(&cfg, kernel, static_cast<Params>(args)...));
}
// kernel<<<grid, block, smem, ctx.stream()>>>(args...) as a programmatic dependent launch where
// ctx's policy has them on; the kernel must begin with wait_for_producer().
template <class... Params, class... Args>
void launch_after(void (*kernel)(Params...), dim3 grid, dim3 block, std::size_t smem, const Context& ctx,
                  const Args&... args) {
  cudaLaunchConfig_t cfg{};
  cfg.gridDim = grid;
  cfg.blockDim = block;
  cfg.dynamicSmemBytes = smem;
  cfg.stream = ctx.stream();
  launch_programmatic(cfg, ctx.policy().programmatic_launch, kernel, args...);
}

// Element-wise work over rows x n: f.pack(r, c) handles columns [c, c + 8) of row r with
// 16-byte accesses, f.one(r, c) a single element. One thread per pack (or element), grid-stride.
template <class F>
__global__ void for_each_pack_kernel(std::int64_t rows, std::int64_t n, F f) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t per_row = n / kPack, total = rows * per_row;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::int64_t r = i / per_row;
    f.pack(r, (i - r * per_row) * kPack);
  }
}
template <class F>
__global__ void for_each_one_kernel(std::int64_t rows, std::int64_t n, F f) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t total = rows * n;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::int64_t r = i / n;
    f.one(r, i - r * n);
  }
}

// Runs f over rows x n, in packs when `packed` (n % 8 == 0 and 16-byte aligned operands).
template <class F>
void for_each(const Context& ctx, std::int64_t rows, std::int64_t n, bool packed, const F& f) {
  if (rows <= 0 || n <= 0) return;
  constexpr int threads = 256;
  if (packed)
    launch_after(for_each_pack_kernel<F>, grid_for(rows * (n / kPack), threads), threads, 0, ctx, rows, n, f);
  else
    launch_after(for_each_one_kernel<F>, grid_for(rows * n, threads), threads, 0, ctx, rows, n, f);
}

// Named barrier `id` (1..15; 0 is __syncthreads) over `threads` threads of the block (a
// multiple of 32), e.g. one warp group's own.
__device__ __forceinline__ void named_barrier(int id, int threads) {
  asm volatile("bar.sync %0, %1;\n" ::"r"(id), "r"(threads) : "memory");
}

// Lets `Kernel` use `bytes` (> 48 KiB) of dynamic shared memory on the current device; set once
// per kernel and device. The attribute is the device's: a tensor-parallel group's threads launch
// the same kernels on several GPUs, and a launch on a GPU that never had it set is refused.
template <auto Kernel>
void allow_dynamic_smem(int bytes) {
  static std::once_flag done[kMaxDevices];
  int device = 0;
  EPONA_CUDA_CHECK(cudaGetDevice(&device));
  EPONA_CHECK(device >= 0 && device < kMaxDevices, "CUDA device ", device, " out of range (at most ", kMaxDevices,
              " devices)");
  std::call_once(done[device], [bytes] {
    EPONA_CUDA_CHECK(cudaFuncSetAttribute(Kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, bytes));
  });
}

}  // namespace detail


}  // namespace epona::cuda
