// epona/cuda/pointwise/activation.cuh — element-wise activations on the GPU, in place: exact GELU
// (erf; the MST's MLP and nn.GELU()), tanh GELU (the DiTs' MLPs) and SiLU, computed in
// float32 on float32 or bf16 storage. The same functors are the GEMM's own epilogues.
// Large bf16 -> bf16 maps read a 65536-entry table of the function instead (a bf16 input has
// only 2^16 values): the same bits as computing it, at memory speed instead of erff's cost.
#pragma once

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "epona/core/env.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace detail {

// Each op names its bf16 lookup table (a key of the context's constant tables).
struct GeluErfOp {
  static constexpr const char* table = "gelu_erf_bf16";
  __device__ float operator()(float v) const { return 0.5f * v * (1.0f + erff(v * 0.70710678118654752f)); }
};
struct GeluTanhOp {
  static constexpr const char* table = "gelu_tanh_bf16";
  __device__ float operator()(float v) const {
    constexpr float k = 0.7978845608028654f;  // sqrt(2/pi)
    return 0.5f * v * (1.0f + tanhf(k * (v + 0.044715f * v * v * v)));
  }
};
struct Identity {
  __device__ float operator()(float v) const { return v; }
};
struct SiluOp {
  static constexpr const char* table = "silu_bf16";
  __device__ float operator()(float v) const { return v / (1.0f + expf(-v)); }
};

// y[i] = op(x[i]) over one row of n elements.
template <class TX, class TY, class Op>
struct MapEach {
  const TX* x;
  TY* y;
  Op op;
  __device__ void pack(std::int64_t, std::int64_t c) const {
    float v[kPack];
    load8(x + c, v);
#pragma unroll
    for (int i = 0; i < kPack; ++i) v[i] = op(v[i]);
    store8(y + c, v);
  }
  __device__ void one(std::int64_t, std::int64_t c) const { y[c] = from_f32<TY>(op(to_f32(x[c]))); }
};

// ---- bf16 lookup tables -----------------------------------------------------------------
inline constexpr int kBf16Values = 1 << 16;
inline constexpr int kTableBytes = kBf16Values * 2;  // 128 KiB: one block's shared memory
inline constexpr int kTableThreads = 1024;
inline constexpr int kTableUnroll = 4;                   // 16-byte packs in flight per thread
inline constexpr std::int64_t kTableMinElements = std::int64_t{1} << 22;  // below: the table copy costs more

// table[b] = op(the bf16 with bits b), rounded to bf16 exactly as MapEach stores it.
template <class Op>
__global__ void build_bf16_table_kernel(std::uint16_t* table, Op op) {
  const int b = blockIdx.x * blockDim.x + threadIdx.x;
  if (b >= kBf16Values) return;
  bf16 v;
  v.bits = static_cast<std::uint16_t>(b);
  table[b] = from_f32<bf16>(op(to_f32(v))).bits;
}

// Two bf16 in one word, each replaced by its table entry.
__device__ __forceinline__ unsigned look_up_pair(const std::uint16_t* lut, unsigned w) {
  return lut[w & 0xffffu] | (static_cast<unsigned>(lut[w >> 16]) << 16);
}

// y = table[x] over `packs` 16-byte packs of bf16: the table is copied into shared memory
// once per block (one block per multiprocessor) while the first loads are in flight, then a
// grid-stride walk issues the next kTableUnroll loads of each thread before it looks up and
// stores the current ones (loading after the stores took 55 µs for the MST's 5150 x 8192 on
// the H200, this 50-52; a copy of the same bytes takes 46.5). x and y may be the same buffer:
// a pack is read before it is written, by the same thread. reverse: pack i is pack
// packs - 1 - i (KernelPolicy::reversed_passes).
// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void __launch_bounds__(kTableThreads, 1)
    table_map_kernel(const uint4* __restrict__ table, const uint4* x, uint4* y, std::int64_t packs, bool reverse) {
  extern __shared__ uint4 lut_packs[];
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  std::int64_t base = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x;
  uint4 now[kTableUnroll], next[kTableUnroll];
  const auto load = [&](uint4(&v)[kTableUnroll], std::int64_t from) {
#pragma unroll
    for (int u = 0; u < kTableUnroll; ++u)
      if (from + u * stride < packs) v[u] = x[pass_index(from + u * stride, packs, reverse)];
  };
  load(now, base);
  for (int i = threadIdx.x; i < kTableBytes / 16; i += blockDim.x) lut_packs[i] = table[i];
  __syncthreads();
  const auto* lut = reinterpret_cast<const std::uint16_t*>(lut_packs);
  for (; base < packs; base += stride * kTableUnroll) {
    load(next, base + stride * kTableUnroll);
#pragma unroll
    for (int u = 0; u < kTableUnroll; ++u) {
      if (base + u * stride < packs)
        y[pass_index(base + u * stride, packs, reverse)] =
            make_uint4(look_up_pair(lut, now[u].x), look_up_pair(lut, now[u].y), look_up_pair(lut, now[u].z),
                       look_up_pair(lut, now[u].w));
      now[u] = next[u];
    }
  }
}

// The context's table of `op` (named Op::table), built on first use; null while the stream is
// being captured and the table does not exist yet (a graph must not depend on a one-time fill).
template <class Op>
const std::uint16_t* bf16_table(Context& ctx, Op op) {
  const char* name = Op::table;
  bool created = false;
  if (detail::capturing(ctx.stream())) {
    // Only look: creating would allocate and fill inside the graph.
    if (!ctx.has_constant_table(name)) return nullptr;
  }
  auto* table = static_cast<std::uint16_t*>(ctx.constant_table(name, kTableBytes, &created));
  if (created) {
    build_bf16_table_kernel<<<kBf16Values / 256, 256, 0, ctx.stream()>>>(table, op);
    EPONA_CUDA_CHECK_LAUNCH();
  }
  return table;
}

// y[i] = op(x[i]); x and y may be the same buffer.
template <class TX, class TY, class Op>
void map(Context& ctx, const TX* x, TY* y, std::int64_t n, Op op) {
  static_assert(is_device_float<TX> && is_device_float<TY>, "activations take float or bf16");
  EPONA_CHECK(n >= 0, "activation: negative element count ", n);
  for_each(ctx, 1, n, packable(x, n, n) && packable(y, n, n), MapEach<TX, TY, Op>{x, y, op});
}

// map() for bf16 -> bf16, through op's table where that pays (large, packable, a
// table available); bit-identical to map() either way. ctx.policy().activation_tables off
// (EPONA_CUDA_TABLES=0) turns the tables off (to time the direct path in the same binary).
template <class Op>
void map_bf16(Context& ctx, const bf16* x, bf16* y, std::int64_t n, Op op) {
  const bool large = ctx.policy().activation_tables && n >= kTableMinElements && packable(x, n, n) && packable(y, n, n);
  const std::uint16_t* table = large ? bf16_table(ctx, op) : nullptr;
  if (!table) return map(ctx, x, y, n, op);
  allow_dynamic_smem<table_map_kernel<>>(kTableBytes);
  const std::int64_t packs = n / kPack;
  const auto blocks = std::min<std::int64_t>(ctx.info().multiprocessors, (packs + kTableThreads - 1) / kTableThreads);
  table_map_kernel<><<<static_cast<unsigned>(blocks), kTableThreads, kTableBytes, ctx.stream()>>>(
      reinterpret_cast<const uint4*>(table), reinterpret_cast<const uint4*>(x), reinterpret_cast<uint4*>(y), packs,
      ctx.policy().reversed_passes);
  EPONA_CUDA_CHECK_LAUNCH();
}

// In place, by the table for bf16.
template <class T, class Op>
void map_in_place(Context& ctx, T* x, std::int64_t n, Op op) {
  if constexpr (std::is_same_v<T, bf16>)
    map_bf16(ctx, x, x, n, op);
  else
    map(ctx, x, x, n, op);
}

}  // namespace detail

template <class T> void gelu_erf(Context& ctx, T* x, std::int64_t n) {
  detail::map_in_place(ctx, x, n, detail::GeluErfOp{});
}
template <class T> void gelu_tanh(Context& ctx, T* x, std::int64_t n) {
  detail::map_in_place(ctx, x, n, detail::GeluTanhOp{});
}
template <class T> void silu(Context& ctx, T* x, std::int64_t n) {
  detail::map_in_place(ctx, x, n, detail::SiluOp{});
}

// y = silu(x) into a separate buffer (modulation inputs keep the original vector).
template <class TX, class TY>
void silu_to(Context& ctx, const TX* x, TY* y, std::int64_t n) {
  detail::map(ctx, x, y, n, detail::SiluOp{});
}

}  // namespace epona::cuda
