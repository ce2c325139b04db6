// epona/cuda/pointwise/copy_convert_axpy.cuh — the kernels the world-model layers need beyond the phase-1 op
// contract, mirroring epona/cpu/copy_fill_axpy.hpp: device copies (dense and strided 2-D),
// float32 -> storage-type conversion (what autocast does to a float32 input of a bf16 GEMM)
// and the Euler update of the samplers, x += round(a·v) with the step formed in v's type, alone
// or fused with the conversion of the new state (one pass per step instead of two).
#pragma once

#include <cstdint>
#include <type_traits>

#include "epona/cuda/pointwise/activation.cuh"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

// dst[i] = src[i] for i < n, asynchronous (device to device).
template <class T>
void copy(Context& ctx, const T* src, T* dst, std::int64_t n) {
  EPONA_CHECK(n >= 0, "copy: negative element count ", n);
  if (n == 0 || src == dst) return;
  EPONA_CUDA_CHECK(cudaMemcpyAsync(dst, src, static_cast<std::size_t>(n) * sizeof(T), cudaMemcpyDeviceToDevice,
                                   ctx.stream()));
}

// dst[r * dst_stride + c] = src[r * src_stride + c] for r < rows, c < cols (non-overlapping).
template <class T>
void copy_rows(Context& ctx, const T* src, std::int64_t src_stride, T* dst, std::int64_t dst_stride, std::int64_t rows,
               std::int64_t cols) {
  EPONA_CHECK(rows >= 0 && cols >= 0 && src_stride >= cols && dst_stride >= cols, "copy_rows: rows ", rows, ", cols ",
              cols, ", strides ", src_stride, "/", dst_stride);
  if (rows == 0 || cols == 0) return;
  EPONA_CUDA_CHECK(cudaMemcpy2DAsync(dst, static_cast<std::size_t>(dst_stride) * sizeof(T), src,
                                     static_cast<std::size_t>(src_stride) * sizeof(T),
                                     static_cast<std::size_t>(cols) * sizeof(T), static_cast<std::size_t>(rows),
                                     cudaMemcpyDeviceToDevice, ctx.stream()));
}

namespace detail {

struct IdentityOp {
  __device__ float operator()(float v) const { return v; }
};

// x[i] += round_V(a · v[i]): PyTorch's `x + dt * v` with a float32 state x and a velocity of
// type V is two kernels, the product rounded to V (bf16 under autocast) before the add.
// __fmul_rn/__fadd_rn keep the two roundings (no contraction into an FMA). With xc (type C,
// else null), the updated state rounded to C is stored there too: the next step's GEMM operand
// (what `convert` makes of it), so the sampler needs no separate conversion pass per step.
template <class V, class C = float>
struct EulerEach {
  float* x;
  const V* v;
  float a;
  C* xc = nullptr;
  __device__ void pack(std::int64_t, std::int64_t c) const {
    float xs[kPack], vs[kPack];
    load8(x + c, xs);
    load8(v + c, vs);
#pragma unroll
    for (int i = 0; i < kPack; ++i) xs[i] = __fadd_rn(xs[i], round_to<V>(__fmul_rn(a, vs[i])));
    store8(x + c, xs);
    if (xc) store8(xc + c, xs);
  }
  __device__ void one(std::int64_t, std::int64_t c) const {
    const float updated = __fadd_rn(x[c], round_to<V>(__fmul_rn(a, to_f32(v[c]))));
    x[c] = updated;
    if (xc) xc[c] = from_f32<C>(updated);
  }
};

}  // namespace detail

// dst[i] = src[i] rounded to T (bf16: nearest even); a copy when T is float.
template <class TS, class TD>
void convert(Context& ctx, const TS* src, TD* dst, std::int64_t n) {
  if constexpr (std::is_same_v<TS, TD>) {
    copy(ctx, src, dst, n);
  } else {
    detail::map(ctx, src, dst, n, detail::IdentityOp{});
  }
}

// x += a · v (the sampler's Euler step), the product rounded to V first.
template <class V>
void axpy(Context& ctx, float* x, const V* v, float a, std::int64_t n) {
  static_assert(is_device_float<V>, "axpy takes a float or bf16 velocity");
  EPONA_CHECK(n >= 0 && x != nullptr && v != nullptr, "axpy: bad arguments (n ", n, ")");
  const bool packed = detail::packable(x, n, n) && detail::packable(v, n, n);
  detail::for_each(ctx, 1, n, packed, detail::EulerEach<V>{x, v, a});
}

// axpy, then xc[i] = x[i] rounded to C (nearest even): the Euler step fused with the conversion
// of the new state into the next velocity evaluation's input type.
template <class V, class C>
void axpy_convert(Context& ctx, float* x, const V* v, float a, C* xc, std::int64_t n) {
  static_assert(is_device_float<V> && is_device_float<C>, "axpy_convert takes float or bf16");
  EPONA_CHECK(n >= 0 && x != nullptr && v != nullptr && xc != nullptr, "axpy_convert: bad arguments (n ", n, ")");
  const bool packed = detail::packable(x, n, n) && detail::packable(v, n, n) && detail::packable(xc, n, n);
  detail::for_each(ctx, 1, n, packed, detail::EulerEach<V, C>{x, v, a, xc});
}

}  // namespace epona::cuda
