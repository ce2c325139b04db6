// Tests for epona/cpu/norm.hpp: LayerNorm (each affine combination), LayerNorm + adaLN
// modulation and per-head RMSNorm against float64 loops, on odd widths (SIMD tails).
// Tolerance: max |got − ref| / max |ref| <= 1e-6 (float32 statistics, as torch).
#include <doctest/doctest.h>

#include <cmath>

#include "epona/cpu/norm.hpp"
#include "testing.hpp"

using namespace epona;

namespace {
struct Moments {
  double mean, rstd;
};
Moments moments_ref(const float* x, std::int64_t n, double eps) {
  double s = 0, v = 0;
  for (std::int64_t i = 0; i < n; ++i) s += x[i];
  const double m = s / static_cast<double>(n);
  for (std::int64_t i = 0; i < n; ++i) v += (x[i] - m) * (x[i] - m);
  return {m, 1.0 / std::sqrt(v / static_cast<double>(n) + eps)};
}
}  // namespace

TEST_CASE("layer_norm with and without affine, out of place and in place") {
  cpu::Context ctx;
  const std::int64_t rows = 5;
  for (auto n : test::odd_sizes()) {
    // A large common offset checks the two-pass variance (one pass would cancel badly).
    auto x = test::random_floats(static_cast<std::size_t>(rows * n), 11, 2.f, 4.f);
    const auto w = test::random_floats(static_cast<std::size_t>(n), 12, 0.5f, 1.5f);
    const auto b = test::random_floats(static_cast<std::size_t>(n), 13);
    for (int affine = 0; affine < 4; ++affine) {
      const float* wp = (affine & 1) ? w.data() : nullptr;
      const float* bp = (affine & 2) ? b.data() : nullptr;
      std::vector<double> ref(x.size());
      for (std::int64_t r = 0; r < rows; ++r) {
        const auto mo = moments_ref(x.data() + r * n, n, 1e-5);
        for (std::int64_t i = 0; i < n; ++i)
          ref[r * n + i] = (x[r * n + i] - mo.mean) * mo.rstd * (wp ? wp[i] : 1.0) + (bp ? bp[i] : 0.0);
      }
      std::vector<float> y(x.size());
      cpu::layer_norm(ctx, x.data(), y.data(), rows, n, wp, bp, 1e-5f);
      CAPTURE(n);
      CAPTURE(affine);
      if (n == 1) {  // variance 0: (x − mean)·rstd = 0 exactly, leaving the bias
        CHECK(test::rel_max(y, ref) <= 1e-6);
        continue;
      }
      CHECK(test::rel_max(y, ref) <= 1e-6);
      auto z = x;  // in place
      cpu::layer_norm(ctx, z.data(), z.data(), rows, n, wp, bp, 1e-5f);
      CHECK(z == y);
    }
  }
}

TEST_CASE("layer_norm on many rows (threaded path) and with a large eps") {
  cpu::Context ctx;
  const std::int64_t rows = 515, n = 131;
  const auto x = test::random_floats(static_cast<std::size_t>(rows * n), 21, -3.f, 3.f);
  std::vector<double> ref(x.size());
  for (std::int64_t r = 0; r < rows; ++r) {
    const auto mo = moments_ref(x.data() + r * n, n, 0.5);
    for (std::int64_t i = 0; i < n; ++i) ref[r * n + i] = (x[r * n + i] - mo.mean) * mo.rstd;
  }
  std::vector<float> y(x.size());
  cpu::layer_norm(ctx, x.data(), y.data(), rows, n, nullptr, nullptr, 0.5f);
  CHECK(test::rel_max(y, ref) <= 1e-6);
}

TEST_CASE("layer_norm_modulate = (1 + scale)·LN(x) + shift") {
  cpu::Context ctx;
  const std::int64_t rows = 7;
  for (auto n : test::odd_sizes()) {
    if (n == 1) continue;
    const auto x = test::random_floats(static_cast<std::size_t>(rows * n), 31, -2.f, 5.f);
    const auto shift = test::random_floats(static_cast<std::size_t>(n), 32);
    const auto scale = test::random_floats(static_cast<std::size_t>(n), 33, -0.5f, 0.5f);
    std::vector<double> ref(x.size());
    for (std::int64_t r = 0; r < rows; ++r) {
      const auto mo = moments_ref(x.data() + r * n, n, 1e-6);
      for (std::int64_t i = 0; i < n; ++i)
        ref[r * n + i] = (1.0 + scale[i]) * ((x[r * n + i] - mo.mean) * mo.rstd) + shift[i];
    }
    std::vector<float> y(x.size());
    cpu::layer_norm_modulate(ctx, x.data(), y.data(), rows, n, shift.data(), scale.data(), 1e-6f);
    CAPTURE(n);
    CHECK(test::rel_max(y, ref) <= 1e-6);
  }
}

TEST_CASE("rms_norm_heads per token and head, strided rows") {
  cpu::Context ctx;
  for (std::int64_t head_dim : {1, 4, 13, 16, 24, 32, 64, 128}) {
    const std::int64_t rows = 9, heads = 3, row_stride = heads * head_dim + 5;  // padding between tokens
    const auto x = test::random_floats(static_cast<std::size_t>(rows * row_stride), 41, -3.f, 3.f);
    const auto scale = test::random_floats(static_cast<std::size_t>(head_dim), 42, 0.5f, 2.f);
    std::vector<double> ref(x.begin(), x.end());
    for (std::int64_t r = 0; r < rows; ++r)
      for (std::int64_t h = 0; h < heads; ++h) {
        const std::int64_t o = r * row_stride + h * head_dim;
        double ss = 0;
        for (std::int64_t i = 0; i < head_dim; ++i) ss += double(x[o + i]) * x[o + i];
        const double rr = 1.0 / std::sqrt(ss / static_cast<double>(head_dim) + 1e-6);
        for (std::int64_t i = 0; i < head_dim; ++i) ref[o + i] = x[o + i] * rr * scale[i];
      }
    auto y = x;
    cpu::rms_norm_heads(ctx, y.data(), rows, row_stride, heads, head_dim, scale.data(), 1e-6f);
    CAPTURE(head_dim);
    CHECK(test::rel_max(y, ref) <= 1e-6);
    for (std::int64_t r = 0; r < rows; ++r)  // the padding between tokens is untouched
      for (std::int64_t i = heads * head_dim; i < row_stride; ++i) CHECK(y[r * row_stride + i] == x[r * row_stride + i]);
  }
}
