// epona/cpu/norm.hpp — normalisations over the last dimension: LayerNorm (affine or not),
// LayerNorm fused with adaLN modulation ((1 + scale) * LN(x) + shift, the DiT blocks), and
// per-head RMSNorm with a learned scale (the DiTs' QK-norm). Statistics in float32 with a
// two-pass mean/variance (biased variance, as torch.layer_norm).
#pragma once

#include <cmath>
#include <cstdint>

#include "epona/cpu/context.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

namespace detail {
struct RowMoments {
  float mean, rstd;
};
// Two passes over the row (mean, then the mean of squared deviations): biased variance, eps
// inside the square root, as torch.layer_norm; exact 1/sqrt (never the approximate rsqrt).
inline RowMoments row_moments(const float* x, std::int64_t n, float eps) {
  using simd::Batch;
  const float mean = simd::sum(x, n) / static_cast<float>(n);
  const Batch m(mean);
  const float var = simd::sum_of(x, n, [m](const Batch& v) { return (v - m) * (v - m); }) / static_cast<float>(n);
  return {mean, 1.0f / std::sqrt(var + eps)};
}
}  // namespace detail

// y[m, :] = (x[m, :] - mean) * rstd * weight + bias over rows of width n. weight/bias may be
// null (no affine). x and y may alias.
inline void layer_norm(Context&, const float* x, float* y, std::int64_t rows, std::int64_t n, const float* weight,
                       const float* bias, float eps) {
  using simd::Batch;
  simd::for_each_row(rows, n, [=](std::int64_t r) {
    const float* xr = x + r * n;
    const auto [mean, rstd] = detail::row_moments(xr, n, eps);
    const Batch m(mean), s(rstd);
    float* yr = y + r * n;
    if (weight && bias)
      simd::map(n, yr, [=](const Batch& v, const Batch& w, const Batch& b) { return (v - m) * s * w + b; }, xr, weight, bias);
    else if (weight)
      simd::map(n, yr, [=](const Batch& v, const Batch& w) { return (v - m) * s * w; }, xr, weight);
    else if (bias)
      simd::map(n, yr, [=](const Batch& v, const Batch& b) { return (v - m) * s + b; }, xr, bias);
    else
      simd::map(n, yr, [=](const Batch& v) { return (v - m) * s; }, xr);
  });
}

// y = (1 + scale) * LN(x) + shift, LN without affine; shift/scale of width n, shared by all rows.
inline void layer_norm_modulate(Context&, const float* x, float* y, std::int64_t rows, std::int64_t n,
                                const float* shift, const float* scale, float eps) {
  using simd::Batch;
  simd::for_each_row(rows, n, [=](std::int64_t r) {
    const float* xr = x + r * n;
    const auto [mean, rstd] = detail::row_moments(xr, n, eps);
    const Batch m(mean), s(rstd);
    simd::map(n, y + r * n, [=](const Batch& v, const Batch& sc, const Batch& sh) {
      return (Batch(1.f) + sc) * ((v - m) * s) + sh;
    }, xr, scale, shift);
  });
}

// In place, per token and head: x_h = x_h * rsqrt(mean(x_h^2) + eps) * scale, where token r's
// heads start at x + r * row_stride and are head_dim wide, `heads` of them side by side.
inline void rms_norm_heads(Context&, float* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                           std::int64_t head_dim, const float* scale, float eps) {
  using simd::Batch;
  simd::for_each_row(rows, heads * head_dim, [=](std::int64_t r) {
    for (std::int64_t h = 0; h < heads; ++h) {
      float* p = x + r * row_stride + h * head_dim;
      const float ms = simd::sum_of(p, head_dim, [](const Batch& v) { return v * v; }) / static_cast<float>(head_dim);
      const Batch rr(1.0f / std::sqrt(ms + eps));
      // (x · rrms) first, then · scale: the official order (the product is cast before scaling).
      simd::map(head_dim, p, [rr](const Batch& v, const Batch& sc) { return (v * rr) * sc; }, p, scale);
    }
  });
}

}  // namespace epona::cpu
