// epona/cpu/norm.hpp — normalisations over the last dimension: LayerNorm (affine or not),
// LayerNorm fused with adaLN modulation ((1 + scale) * LN(x) + shift, the DiT blocks), and
// per-head RMSNorm with a learned scale (the DiTs' QK-norm). Statistics in float32 with a
// two-pass mean/variance (biased variance, as torch.layer_norm).
#pragma once

#include <cmath>
#include <cstdint>

#include "epona/cpu/context.hpp"

namespace epona::cpu {

namespace detail {
inline void row_moments(const float* x, std::int64_t n, float& mean, float& rstd, float eps) {
  double s = 0;
  for (std::int64_t i = 0; i < n; ++i) s += x[i];
  const float m = static_cast<float>(s / n);
  double v = 0;
  for (std::int64_t i = 0; i < n; ++i) v += double(x[i] - m) * double(x[i] - m);
  mean = m;
  rstd = 1.0f / std::sqrt(static_cast<float>(v / n) + eps);
}
}  // namespace detail

// y[m, :] = (x[m, :] - mean) * rstd * weight + bias over rows of width n. weight/bias may be
// null (no affine). x and y may alias.
inline void layer_norm(Context&, const float* x, float* y, std::int64_t rows, std::int64_t n, const float* weight,
                       const float* bias, float eps) {
#pragma omp parallel for
  for (std::int64_t r = 0; r < rows; ++r) {
    const float* xr = x + r * n;
    float* yr = y + r * n;
    float mean, rstd;
    detail::row_moments(xr, n, mean, rstd, eps);
    for (std::int64_t i = 0; i < n; ++i) {
      float v = (xr[i] - mean) * rstd;
      if (weight) v = v * weight[i];
      if (bias) v = v + bias[i];
      yr[i] = v;
    }
  }
}

// y = (1 + scale) * LN(x) + shift, LN without affine; shift/scale of width n, shared by all rows.
inline void layer_norm_modulate(Context&, const float* x, float* y, std::int64_t rows, std::int64_t n,
                                const float* shift, const float* scale, float eps) {
#pragma omp parallel for
  for (std::int64_t r = 0; r < rows; ++r) {
    const float* xr = x + r * n;
    float* yr = y + r * n;
    float mean, rstd;
    detail::row_moments(xr, n, mean, rstd, eps);
    for (std::int64_t i = 0; i < n; ++i) yr[i] = (1.0f + scale[i]) * ((xr[i] - mean) * rstd) + shift[i];
  }
}

// In place, per token and head: x_h = x_h * rsqrt(mean(x_h^2) + eps) * scale, where token r's
// heads start at x + r * row_stride and are head_dim wide, `heads` of them side by side.
inline void rms_norm_heads(Context&, float* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                           std::int64_t head_dim, const float* scale, float eps) {
#pragma omp parallel for
  for (std::int64_t r = 0; r < rows; ++r)
    for (std::int64_t h = 0; h < heads; ++h) {
      float* p = x + r * row_stride + h * head_dim;
      float ss = 0;
      for (std::int64_t i = 0; i < head_dim; ++i) ss += p[i] * p[i];
      const float rr = 1.0f / std::sqrt(ss / static_cast<float>(head_dim) + eps);
      for (std::int64_t i = 0; i < head_dim; ++i) p[i] = (p[i] * rr) * scale[i];
    }
}

}  // namespace epona::cpu
