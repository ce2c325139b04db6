// epona/cuda/activation.cuh — element-wise activations on the GPU, in place: exact GELU
// (erf; the MST's MLP and nn.GELU()), tanh GELU (the DiTs' MLPs) and SiLU, computed in
// float32 on float32 or bf16 storage. The same functors are the GEMM's own epilogues.
#pragma once

#include <cstdint>

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

// y[i] = op(x[i]); x and y may be the same buffer.
template <class TX, class TY, class Op>
void map(Context& ctx, const TX* x, TY* y, std::int64_t n, Op op) {
  static_assert(is_device_float<TX> && is_device_float<TY>, "activations take float or bf16");
  EPONA_CHECK(n >= 0, "activation: negative element count ", n);
  for_each(ctx.stream(), 1, n, packable(x, n, n) && packable(y, n, n), MapEach<TX, TY, Op>{x, y, op});
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
