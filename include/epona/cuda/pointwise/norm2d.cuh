// epona/cuda/pointwise/norm2d.cuh — the DC-AE's channel norms on the GPU over channels-last maps, as
// cpu/conv.hpp's: RMSNorm2d (TritonRMSNorm2d: per pixel over channels, no mean subtraction,
// weight and bias) and eval BatchNorm2d, plus the fused `residual += norm(branch)` of every
// DC-AE block's post-norm branch. One warp per pixel row; statistics in float32.
#pragma once

#include <cstdint>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace norm2d_detail {

// Parameters of one norm: RMS when mean/var are null, BatchNorm (running statistics) otherwise.
struct Params {
  const float *weight, *bias, *mean, *var;
  float eps;
};

// What a warp writes for its row: y = norm(x), or residual = residual + norm(x) (y unused).
template <class T>
struct Out {
  T* y;
  T* residual;
  __device__ float finish(float normed, const T* slot_residual) const {
    if (!residual) return normed;
    return detail::to_f32(*slot_residual) + detail::round_to<T>(normed);
  }
};

__device__ __forceinline__ float normalise(float v, int c, float rr, const Params& p) {
  if (p.mean) return (v - p.mean[c]) * (1.0f / sqrtf(p.var[c] + p.eps)) * p.weight[c] + p.bias[c];
  return (v * rr) * p.weight[c] + p.bias[c];
}

// Rows of C % 8 == 0 channels, at most 8·32·kMaxPacks, held in registers (one read, one write).
// A warp takes R rows of P packs per lane at a time and issues all their loads (rows, residuals)
// before the first reduction, so each warp keeps 4 packs per lane in flight (short rows would
// otherwise leave the loads latency-bound).
constexpr int kMaxPacks = 4;
template <class T, int P, int R>
__global__ void norm_rows_packed(const T* __restrict__ x, Out<T> out, std::int64_t rows, int C, Params p) {
  const int lane = threadIdx.x & 31, warps = blockDim.x >> 5;
  const int packs = C / detail::kPack;
  for (std::int64_t row0 = (blockIdx.x * std::int64_t{warps} + (threadIdx.x >> 5)) * R; row0 < rows;
       row0 += std::int64_t{gridDim.x} * warps * R) {
    float v[R][P][detail::kPack], res[R][P][detail::kPack];
#pragma unroll
    for (int r = 0; r < R; ++r) {
      const std::int64_t row = row0 + r;
#pragma unroll
      for (int k = 0; k < P; ++k) {
        const int pk = lane + 32 * k;
        if (row >= rows || pk >= packs) continue;
        detail::load8(x + row * C + pk * detail::kPack, v[r][k]);
        if (out.residual) detail::load8(out.residual + row * C + pk * detail::kPack, res[r][k]);
      }
    }
    float rr[R];
#pragma unroll
    for (int r = 0; r < R; ++r) {
      float ss = 0.f;
      if (!p.mean && row0 + r < rows) {
#pragma unroll
        for (int k = 0; k < P; ++k) {
          if (lane + 32 * k >= packs) continue;
#pragma unroll
          for (int i = 0; i < detail::kPack; ++i) ss += v[r][k][i] * v[r][k][i];
        }
      }
      rr[r] = p.mean ? 0.f : 1.0f / sqrtf(detail::warp_sum(ss) / static_cast<float>(C) + p.eps);
    }
#pragma unroll
    for (int k = 0; k < P; ++k) {
      const int pk = lane + 32 * k;
      if (pk >= packs) continue;
      const int c0 = pk * detail::kPack;
      float w[detail::kPack], b[detail::kPack], m[detail::kPack], inv[detail::kPack];
      detail::load8(p.weight + c0, w);
      detail::load8(p.bias + c0, b);
      if (p.mean) {
        float var[detail::kPack];
        detail::load8(p.mean + c0, m);
        detail::load8(p.var + c0, var);
#pragma unroll
        for (int i = 0; i < detail::kPack; ++i) inv[i] = 1.0f / sqrtf(var[i] + p.eps);
      }
#pragma unroll
      for (int r = 0; r < R; ++r) {
        const std::int64_t row = row0 + r;
        if (row >= rows) continue;
        float o[detail::kPack];
#pragma unroll
        for (int i = 0; i < detail::kPack; ++i) {
          const float n = p.mean ? (v[r][k][i] - m[i]) * inv[i] * w[i] + b[i] : (v[r][k][i] * rr[r]) * w[i] + b[i];
          o[i] = out.residual ? res[r][k][i] + detail::round_to<T>(n) : n;
        }
        detail::store8((out.residual ? out.residual : out.y) + row * C + c0, o);
      }
    }
  }
}

// Any C: two passes over the row in global memory (the second mostly from cache).
template <class T>
__global__ void norm_rows_generic(const T* __restrict__ x, Out<T> out, std::int64_t rows, int C, Params p) {
  const int lane = threadIdx.x & 31, warps = blockDim.x >> 5;
  for (std::int64_t row = blockIdx.x * std::int64_t{warps} + (threadIdx.x >> 5); row < rows;
       row += std::int64_t{gridDim.x} * warps) {
    const T* xr = x + row * C;
    float ss = 0.f;
    if (!p.mean)
      for (int c = lane; c < C; c += 32) {
        const float v = detail::to_f32(xr[c]);
        ss += v * v;
      }
    const float rr = p.mean ? 0.f : 1.0f / sqrtf(detail::warp_sum(ss) / static_cast<float>(C) + p.eps);
    for (int c = lane; c < C; c += 32) {
      const float n = normalise(detail::to_f32(xr[c]), c, rr, p);
      T* slot = (out.residual ? out.residual : out.y) + row * C + c;
      *slot = detail::from_f32<T>(out.finish(n, slot));
    }
  }
}

template <class T>
void launch(Context& ctx, const T* x, Out<T> out, std::int64_t rows, std::int64_t C, const Params& p,
            const char* what) {
  static_assert(is_device_float<T>, "channel norms take float or bf16 maps");
  EPONA_CHECK(rows >= 0 && C > 0 && C <= 0x7fffffff, what, ": bad extent (pixels ", rows, ", channels ", C, ")");
  EPONA_CHECK(x && p.weight && p.bias && (out.y || out.residual), what, ": null input, output or parameter");
  if (rows == 0) return;
  constexpr int threads = 256, warps = threads / 32;
  const unsigned blocks = detail::grid_for((rows + warps - 1) / warps, 1);
  const T* target = out.residual ? out.residual : out.y;
  const std::int64_t packs = C / detail::kPack;
  const bool packed = C % detail::kPack == 0 && packs <= 32 * kMaxPacks && detail::aligned16(x) &&
                      detail::aligned16(target) && detail::aligned16(p.weight) && detail::aligned16(p.bias) &&
                      (!p.mean || (detail::aligned16(p.mean) && detail::aligned16(p.var)));
  const int C32 = static_cast<int>(C);
  const auto grid = [&](int rows_per_warp) {
    return detail::grid_for((rows + std::int64_t{warps} * rows_per_warp - 1) / (std::int64_t{warps} * rows_per_warp), 1);
  };
  if (packed && packs <= 32)
    norm_rows_packed<T, 1, 4><<<grid(4), threads, 0, ctx.stream()>>>(x, out, rows, C32, p);
  else if (packed && packs <= 64)
    norm_rows_packed<T, 2, 2><<<grid(2), threads, 0, ctx.stream()>>>(x, out, rows, C32, p);
  else if (packed)
    norm_rows_packed<T, 4, 1><<<grid(1), threads, 0, ctx.stream()>>>(x, out, rows, C32, p);
  else
    norm_rows_generic<<<blocks, threads, 0, ctx.stream()>>>(x, out, rows, C32, p);
  EPONA_CUDA_CHECK_LAUNCH();
}

// One warp per row: y = x · 1/sqrt(mean(x²) + eps) · weight, computed in float32 from TX, stored as TY.
template <class TX, class TY>
__global__ void rms_rows_kernel(const TX* __restrict__ x, TY* __restrict__ y, std::int64_t rows, int n,
                                const float* __restrict__ weight, float eps) {
  const int lane = threadIdx.x & 31, warps = blockDim.x >> 5;
  for (std::int64_t row = blockIdx.x * std::int64_t{warps} + (threadIdx.x >> 5); row < rows;
       row += std::int64_t{gridDim.x} * warps) {
    const TX* xr = x + row * n;
    float ss = 0.f;
    for (int c = lane; c < n; c += 32) {
      const float v = detail::to_f32(xr[c]);
      ss += v * v;
    }
    const float rr = 1.0f / sqrtf(detail::warp_sum(ss) / static_cast<float>(n) + eps);
    for (int c = lane; c < n; c += 32) y[row * n + c] = detail::from_f32<TY>((detail::to_f32(xr[c]) * rr) * weight[c]);
  }
}

}  // namespace norm2d_detail

// RMSNorm without bias over rows of n (the temporal blocks' attention_norm / ffn_norm): from a
// float32 residual stream into the GEMMs' input type, rounded once (as the reference's float32
// norm followed by autocast's cast).
template <class TX, class TY>
void rms_norm_rows(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const float* weight, float eps) {
  static_assert(is_device_float<TX> && is_device_float<TY>, "rms_norm_rows takes float or bf16");
  EPONA_CHECK(rows >= 0 && n > 0 && n <= 0x7fffffff, "rms_norm_rows: bad extent (rows ", rows, ", width ", n, ")");
  EPONA_CHECK(x && y && weight, "rms_norm_rows: null input, output or weight");
  if (rows == 0) return;
  constexpr int threads = 256, warps = threads / 32;
  norm2d_detail::rms_rows_kernel<<<detail::grid_for((rows + warps - 1) / warps, 1), threads, 0, ctx.stream()>>>(
      x, y, rows, static_cast<int>(n), weight, eps);
  EPONA_CUDA_CHECK_LAUNCH();
}

// RMSNorm2d over channels-last x (N·HW pixel rows of C): y = x · 1/sqrt(mean_c x² + eps) ·
// weight + bias (float32 sums; y may be x). The CPU's argument list (N, C, HW).
template <class T>
void rms_norm_2d(Context& ctx, const T* x, T* y, std::int64_t N, std::int64_t C, std::int64_t HW, const float* weight,
                 const float* bias, float eps) {
  norm2d_detail::launch(ctx, x, norm2d_detail::Out<T>{y, nullptr}, N * HW, C,
                        {weight, bias, nullptr, nullptr, eps}, "rms_norm_2d");
}

// Eval BatchNorm2d: y = (x - mean[c]) / sqrt(var[c] + eps) · weight[c] + bias[c] (y may be x).
template <class T>
void batch_norm_2d(Context& ctx, const T* x, T* y, std::int64_t N, std::int64_t C, std::int64_t HW,
                   const float* weight, const float* bias, const float* mean, const float* var, float eps) {
  EPONA_CHECK(mean && var, "batch_norm_2d: null running statistics");
  norm2d_detail::launch(ctx, x, norm2d_detail::Out<T>{y, nullptr}, N * HW, C, {weight, bias, mean, var, eps},
                        "batch_norm_2d");
}

// residual += norm(branch) over `pixels` rows of C channels in one pass; BatchNorm when mean
// and var are given, RMSNorm2d otherwise. The normalised value is rounded to T before the add,
// as when it is stored first. branch is not modified.
template <class T>
void norm_2d_add(Context& ctx, const T* branch, T* residual, std::int64_t pixels, std::int64_t C, const float* weight,
                 const float* bias, const float* mean, const float* var, float eps) {
  EPONA_CHECK(branch != residual, "norm_2d_add: branch and residual must differ");
  norm2d_detail::launch(ctx, branch, norm2d_detail::Out<T>{nullptr, residual}, pixels, C,
                        {weight, bias, mean, var, eps}, "norm_2d_add");
}

}  // namespace epona::cuda
