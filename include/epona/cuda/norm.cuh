// epona/cuda/norm.cuh — normalisations over the last dimension on the GPU: LayerNorm (affine
// or not), LayerNorm fused with adaLN modulation ((1 + scale) * LN(x) + shift, the DiT blocks:
// one pass instead of three) and per-head RMSNorm (the DiTs' QK-norm, in place on packed QKV).
// Statistics in float32 (two-pass mean/variance, biased variance, as torch.layer_norm).
#pragma once

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "epona/cuda/context.hpp"
#include "epona/cuda/device.cuh"

namespace epona::cuda {

namespace detail {

// Mean and 1/sqrt(var + eps) of one row, computed by the whole block (two passes over x).
template <class TX>
__device__ void row_moments(const TX* x, std::int64_t n, float eps, float& mean, float& rstd, float* scratch) {
  float s = 0;
  for (std::int64_t i = threadIdx.x; i < n; i += blockDim.x) s += to_f32(x[i]);
  mean = block_sum(s, scratch) / static_cast<float>(n);
  float v = 0;
  for (std::int64_t i = threadIdx.x; i < n; i += blockDim.x) {
    const float d = to_f32(x[i]) - mean;
    v += d * d;
  }
  rstd = 1.0f / sqrtf(block_sum(v, scratch) / static_cast<float>(n) + eps);
}

// One block per row. Affine LayerNorm when weight/bias are given; with modulate, shift/scale
// take their place as (1 + scale) * LN(x) + shift, 1 + scale rounded to the parameters'
// storage type as PyTorch does for `1 + scale_tensor`.
template <class TX, class TY, class TP, bool Modulate>
__global__ void layer_norm_kernel(const TX* x, TY* y, std::int64_t n, const TP* mul, const TP* add, float eps) {
  __shared__ float scratch[32];
  const TX* xr = x + blockIdx.x * n;
  TY* yr = y + blockIdx.x * n;
  float mean, rstd;
  row_moments(xr, n, eps, mean, rstd, scratch);
  for (std::int64_t i = threadIdx.x; i < n; i += blockDim.x) {
    float v = (to_f32(xr[i]) - mean) * rstd;
    if constexpr (Modulate) {
      v = round_to<TP>(1.0f + to_f32(mul[i])) * v + to_f32(add[i]);
    } else {
      if (mul) v = v * to_f32(mul[i]);
      if (add) v = v + to_f32(add[i]);
    }
    yr[i] = from_f32<TY>(v);
  }
}

// The same with the row held in registers (read once, written once, 16-byte accesses): for
// n % 8 == 0, n <= 8 * kRowPacks * 256, aligned rows. Up to kRowPacks packs per thread.
constexpr int kRowPacks = 4;
template <class TX, class TY, class TP, bool Modulate>
__global__ void layer_norm_packed_kernel(const TX* x, TY* y, std::int64_t n, const TP* mul, const TP* add, float eps) {
  __shared__ float scratch[32];
  const TX* xr = x + blockIdx.x * n;
  TY* yr = y + blockIdx.x * n;
  const int packs = static_cast<int>(n / kPack);
  float v[kRowPacks][kPack];
  float s = 0;
#pragma unroll
  for (int k = 0; k < kRowPacks; ++k) {
    const int p = threadIdx.x + k * blockDim.x;
    if (p >= packs) continue;
    load8(xr + p * kPack, v[k]);
#pragma unroll
    for (int i = 0; i < kPack; ++i) s += v[k][i];
  }
  const float mean = block_sum(s, scratch) / static_cast<float>(n);
  float q = 0;
#pragma unroll
  for (int k = 0; k < kRowPacks; ++k) {
    if (threadIdx.x + k * blockDim.x >= packs) continue;
#pragma unroll
    for (int i = 0; i < kPack; ++i) q += (v[k][i] - mean) * (v[k][i] - mean);
  }
  const float rstd = 1.0f / sqrtf(block_sum(q, scratch) / static_cast<float>(n) + eps);
#pragma unroll
  for (int k = 0; k < kRowPacks; ++k) {
    const int p = threadIdx.x + k * blockDim.x;
    if (p >= packs) continue;
    float m[kPack], a[kPack];
    if (mul) load8(mul + p * kPack, m);
    if (add) load8(add + p * kPack, a);
#pragma unroll
    for (int i = 0; i < kPack; ++i) {
      float o = (v[k][i] - mean) * rstd;
      if constexpr (Modulate) {
        o = round_to<TP>(1.0f + m[i]) * o + a[i];
      } else {
        if (mul) o = o * m[i];
        if (add) o = o + a[i];
      }
      v[k][i] = o;
    }
    store8(yr + p * kPack, v[k]);
  }
}

// One warp per (token, head).
template <class T, class TP>
__global__ void rms_norm_heads_kernel(T* x, std::int64_t rows, std::int64_t row_stride, int heads, int head_dim,
                                      const TP* scale, float eps) {
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;
  if (item >= rows * heads) return;
  const int lane = threadIdx.x & 31;
  T* p = x + (item / heads) * row_stride + (item % heads) * head_dim;
  float ss = 0;
  for (int i = lane; i < head_dim; i += 32) {
    const float v = to_f32(p[i]);
    ss += v * v;
  }
  const float rr = 1.0f / sqrtf(warp_sum(ss) / static_cast<float>(head_dim) + eps);
  // Official QK-norm: (x * rrms).to(x.dtype) * scale — the product is rounded before scaling.
  for (int i = lane; i < head_dim; i += 32) p[i] = from_f32<T>(round_to<T>(to_f32(p[i]) * rr) * to_f32(scale[i]));
}

inline int norm_threads(std::int64_t n) { return n >= 1024 ? 256 : n >= 256 ? 128 : 64; }

template <bool Modulate, class TX, class TY, class TP>
void launch_layer_norm(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const TP* mul,
                       const TP* add, float eps, const char* what) {
  static_assert(is_device_float<TX> && is_device_float<TY> && is_device_float<TP>, "norms take float or bf16");
  EPONA_CHECK(rows >= 0 && n > 0, what, ": bad extent (rows ", rows, ", width ", n, ")");
  EPONA_CHECK(rows <= 0x7fffffff, what, ": ", rows, " rows exceed one launch");
  if (rows == 0) return;
  const std::int64_t packs = n / kPack;
  if (packable(x, n, n) && packable(y, n, n) && packable(mul, n, 0) && packable(add, n, 0) &&
      packs <= 256 * kRowPacks) {
    const int threads = static_cast<int>(std::min<std::int64_t>(256, (packs + 31) / 32 * 32));
    layer_norm_packed_kernel<TX, TY, TP, Modulate>
        <<<static_cast<unsigned>(rows), threads, 0, ctx.stream()>>>(x, y, n, mul, add, eps);
  } else {
    layer_norm_kernel<TX, TY, TP, Modulate>
        <<<static_cast<unsigned>(rows), norm_threads(n), 0, ctx.stream()>>>(x, y, n, mul, add, eps);
  }
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace detail

// y[m, :] = (x[m, :] - mean) * rstd * weight + bias over rows of width n. weight/bias may be
// null (no affine). x and y may alias.
template <class TX, class TY, class TP = float>
void layer_norm(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const TP* weight,
                const std::type_identity_t<TP>* bias, float eps) {
  detail::launch_layer_norm<false>(ctx, x, y, rows, n, weight, bias, eps, "layer_norm");
}

// y = (1 + scale) * LN(x) + shift, LN without affine; shift/scale of width n, shared by all rows.
template <class TX, class TY, class TP>
void layer_norm_modulate(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const TP* shift,
                         const TP* scale, float eps) {
  EPONA_CHECK(shift != nullptr && scale != nullptr, "layer_norm_modulate: null shift or scale");
  detail::launch_layer_norm<true>(ctx, x, y, rows, n, scale, shift, eps, "layer_norm_modulate");
}

// In place, per token and head: x_h = x_h * rsqrt(mean(x_h^2) + eps) * scale, where token r's
// heads start at x + r * row_stride and are head_dim wide, `heads` of them side by side.
template <class T, class TP>
void rms_norm_heads(Context& ctx, T* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                    std::int64_t head_dim, const TP* scale, float eps) {
  static_assert(is_device_float<T> && is_device_float<TP>, "rms_norm_heads takes float or bf16");
  EPONA_CHECK(rows >= 0 && heads > 0 && head_dim > 0 && head_dim <= 0x7fffffff && heads <= 0x7fffffff,
              "rms_norm_heads: bad extent (rows ", rows, ", heads ", heads, ", head_dim ", head_dim, ")");
  EPONA_CHECK(row_stride >= heads * head_dim, "rms_norm_heads: row stride ", row_stride, " is narrower than ",
              heads, " heads of ", head_dim);
  EPONA_CHECK(scale != nullptr, "rms_norm_heads: null scale");
  if (rows == 0) return;
  constexpr int threads = 256, warps = threads / 32;
  const std::int64_t blocks = (rows * heads + warps - 1) / warps;
  EPONA_CHECK(blocks <= 0x7fffffff, "rms_norm_heads: ", rows * heads, " heads exceed one launch");
  detail::rms_norm_heads_kernel<<<static_cast<unsigned>(blocks), threads, 0, ctx.stream()>>>(
      x, rows, row_stride, static_cast<int>(heads), static_cast<int>(head_dim), scale, eps);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda
