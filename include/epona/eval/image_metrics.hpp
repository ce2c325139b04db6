// epona/eval/image_metrics.hpp — frame-quality metrics of generated video against the true
// frames, on 8-bit RGB: PSNR (MAX = 255, the MSE over all pixels and channels) and SSIM as Wang
// et al. 2004 define it (11x11 Gaussian window, sigma 1.5, K1 = 0.01, K2 = 0.03, L = 255,
// population statistics, the mean over the positions where the window fits, i.e. MATLAB's
// 'valid' filtering), computed per RGB channel and averaged — what scikit-image's
// structural_similarity(a, b, channel_axis=2, data_range=255, gaussian_weights=True,
// sigma=1.5, use_sample_covariance=False) reports. Sums run in float64.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/io/image.hpp"

namespace epona::eval {

// PSNR of identical images is infinite; JSON has no infinity, so it is reported as this cap
// (an MSE of 1/1000 of one grey level squared would still read only 78 dB).
inline constexpr double kPsnrCap = 100.0;

inline void check_same_size(const io::Image& a, const io::Image& b, const char* metric) {
  EPONA_CHECK(a.height == b.height && a.width == b.width && a.rgb.size() == b.rgb.size() && !a.rgb.empty(), metric,
              ": the images differ in size (", a.height, "x", a.width, " vs ", b.height, "x", b.width, ")");
}

inline double mean_squared_error(const io::Image& a, const io::Image& b) {
  check_same_size(a, b, "MSE");
  double sum = 0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) {
    const double d = double(a.rgb[i]) - double(b.rgb[i]);
    sum += d * d;
  }
  return sum / double(a.rgb.size());
}

// 10 log10(255^2 / MSE), capped at kPsnrCap.
inline double psnr(const io::Image& a, const io::Image& b) {
  const double mse = mean_squared_error(a, b);
  if (mse == 0) return kPsnrCap;
  return std::min(kPsnrCap, 10.0 * std::log10(255.0 * 255.0 / mse));
}

struct SsimParams {
  int radius = 5;  // window 2 * 5 + 1 = 11
  double sigma = 1.5, k1 = 0.01, k2 = 0.03, range = 255.0;
};

namespace ssim_detail {

inline std::vector<double> gaussian_taps(const SsimParams& p) {
  std::vector<double> w(static_cast<std::size_t>(2 * p.radius + 1));
  double sum = 0;
  for (int i = -p.radius; i <= p.radius; ++i) sum += w[i + p.radius] = std::exp(-double(i * i) / (2 * p.sigma * p.sigma));
  for (auto& v : w) v /= sum;
  return w;
}

// The window-weighted mean at every position where the window fits: (H, W) -> (H - 2r, W - 2r).
// The Gaussian is separable: rows, then columns.
inline std::vector<double> filter_valid(const std::vector<double>& plane, std::int64_t H, std::int64_t W,
                                        const std::vector<double>& taps) {
  const auto k = static_cast<std::int64_t>(taps.size()), Wo = W - k + 1, Ho = H - k + 1;
  std::vector<double> rows(static_cast<std::size_t>(H * Wo)), out(static_cast<std::size_t>(Ho * Wo));
  for (std::int64_t y = 0; y < H; ++y)
    for (std::int64_t x = 0; x < Wo; ++x) {
      double s = 0;
      for (std::int64_t t = 0; t < k; ++t) s += taps[t] * plane[y * W + x + t];
      rows[y * Wo + x] = s;
    }
  for (std::int64_t y = 0; y < Ho; ++y)
    for (std::int64_t x = 0; x < Wo; ++x) {
      double s = 0;
      for (std::int64_t t = 0; t < k; ++t) s += taps[t] * rows[(y + t) * Wo + x];
      out[y * Wo + x] = s;
    }
  return out;
}

// Mean SSIM of one channel.
inline double channel_ssim(const io::Image& a, const io::Image& b, int c, const SsimParams& p) {
  const std::int64_t H = a.height, W = a.width, n = H * W;
  std::vector<double> x(n), y(n), xx(n), yy(n), xy(n);
  for (std::int64_t i = 0; i < n; ++i) {
    x[i] = a.rgb[i * 3 + c], y[i] = b.rgb[i * 3 + c];
    xx[i] = x[i] * x[i], yy[i] = y[i] * y[i], xy[i] = x[i] * y[i];
  }
  const auto taps = gaussian_taps(p);
  const auto mx = filter_valid(x, H, W, taps), my = filter_valid(y, H, W, taps);
  const auto sxx = filter_valid(xx, H, W, taps), syy = filter_valid(yy, H, W, taps), sxy = filter_valid(xy, H, W, taps);
  const double c1 = (p.k1 * p.range) * (p.k1 * p.range), c2 = (p.k2 * p.range) * (p.k2 * p.range);
  double sum = 0;
  for (std::size_t i = 0; i < mx.size(); ++i) {
    const double vx = sxx[i] - mx[i] * mx[i], vy = syy[i] - my[i] * my[i], cov = sxy[i] - mx[i] * my[i];
    sum += ((2 * mx[i] * my[i] + c1) * (2 * cov + c2)) / ((mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2));
  }
  return sum / double(mx.size());
}

}  // namespace ssim_detail

// Mean SSIM over the three RGB channels; 1 for identical images.
inline double ssim(const io::Image& a, const io::Image& b, const SsimParams& p = {}) {
  check_same_size(a, b, "SSIM");
  const std::int64_t window = 2 * p.radius + 1;
  EPONA_CHECK(a.height >= window && a.width >= window, "SSIM: the images (", a.height, "x", a.width,
              ") are smaller than the ", window, "x", window, " window");
  double sum = 0;
  for (int c = 0; c < 3; ++c) sum += ssim_detail::channel_ssim(a, b, c, p);
  return sum / 3.0;
}

}  // namespace epona::eval
