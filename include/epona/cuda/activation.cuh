// epona/cuda/activation.cuh — element-wise activations on the GPU, in place: exact GELU
// (erf; the MST's MLP and nn.GELU()), tanh GELU (the DiTs' MLPs) and SiLU, computed in
// float32 on float32 or bf16 storage. The same functors are the GEMM's own epilogues. Dense
// passes run in 16-byte packs, two per thread in flight, on a grid sized to the GPU.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstdlib>

#include "epona/cuda/context.hpp"
#include "epona/cuda/device.cuh"

namespace epona::cuda {

namespace detail {

struct GeluErfOp {
  __device__ float operator()(float v) const { return 0.5f * v * (1.0f + erff(v * 0.70710678118654752f)); }
};
struct GeluTanhOp {
  __device__ float operator()(float v) const {
    constexpr float k = 0.7978845608028654f;  // sqrt(2/pi)
    return 0.5f * v * (1.0f + tanhf(k * (v + 0.044715f * v * v * v)));
  }
};
struct SiluOp {
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

// y = op(x) over `packs` 16-byte packs: a grid-stride loop with 32-bit indices (no 64-bit
// division per pack) and two packs per thread loaded before either is computed.
template <class TX, class TY, class Op>
__global__ void map_packs_kernel(const TX* x, TY* y, unsigned packs, Op op) {
  const unsigned stride = gridDim.x * blockDim.x;
  for (unsigned i = blockIdx.x * blockDim.x + threadIdx.x; i < packs; i += 2 * stride) {
    const unsigned j = i + stride;
    float a[kPack], b[kPack];
    load8(x + std::size_t{i} * kPack, a);
    if (j < packs) load8(x + std::size_t{j} * kPack, b);
#pragma unroll
    for (int e = 0; e < kPack; ++e) a[e] = op(a[e]);
    store8(y + std::size_t{i} * kPack, a);
    if (j < packs) {
#pragma unroll
      for (int e = 0; e < kPack; ++e) b[e] = op(b[e]);
      store8(y + std::size_t{j} * kPack, b);
    }
  }
}

// The previous path (for_each, one pack per thread), selectable with EPONA_MAP_LEGACY=1 while
// the two are measured side by side.
inline bool legacy_map() {
  static const bool legacy = [] {
    const char* e = std::getenv("EPONA_MAP_LEGACY");
    return e && e[0] == '1';
  }();
  return legacy;
}

// y[i] = op(x[i]); x and y may be the same buffer.
template <class TX, class TY, class Op>
void map(Context& ctx, const TX* x, TY* y, std::int64_t n, Op op) {
  static_assert(is_device_float<TX> && is_device_float<TY>, "activations take float or bf16");
  EPONA_CHECK(n >= 0, "activation: negative element count ", n);
  const bool packed = packable(x, n, n) && packable(y, n, n);
  const std::int64_t packs = n / kPack;
  if (!packed || legacy_map() || packs == 0 || packs > 0x7fffffff) {
    for_each(ctx.stream(), 1, n, packed, MapEach<TX, TY, Op>{x, y, op});
    return;
  }
  constexpr int threads = 256;
  const unsigned blocks = static_cast<unsigned>(
      std::clamp<std::int64_t>((packs + 2 * threads - 1) / (2 * threads), 1, 8L * ctx.info().multiprocessors));
  map_packs_kernel<<<blocks, threads, 0, ctx.stream()>>>(x, y, static_cast<unsigned>(packs), op);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace detail

template <class T> void gelu_erf(Context& ctx, T* x, std::int64_t n) { detail::map(ctx, x, x, n, detail::GeluErfOp{}); }
template <class T> void gelu_tanh(Context& ctx, T* x, std::int64_t n) { detail::map(ctx, x, x, n, detail::GeluTanhOp{}); }
template <class T> void silu(Context& ctx, T* x, std::int64_t n) { detail::map(ctx, x, x, n, detail::SiluOp{}); }

// y = silu(x) into a separate buffer (modulation inputs keep the original vector).
template <class TX, class TY>
void silu_to(Context& ctx, const TX* x, TY* y, std::int64_t n) {
  detail::map(ctx, x, y, n, detail::SiluOp{});
}

}  // namespace epona::cuda
