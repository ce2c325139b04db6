// Tests for epona/cpu/rope.hpp: interleaved-pair rotary embedding against a float64 loop,
// for head dims around the SIMD widths, several heads sharing one table, strided tokens.
// Tolerance: max |got − ref| / max |ref| <= 1e-6.
#include <doctest/doctest.h>

#include <cmath>

#include "epona/core/error.hpp"
#include "epona/cpu/rope.hpp"
#include "testing.hpp"

using namespace epona;

TEST_CASE("apply_rope rotates interleaved pairs with a per-token table shared by heads") {
  cpu::Context ctx;
  for (std::int64_t head_dim : {2, 4, 6, 8, 24, 32, 40, 64, 128}) {
    const std::int64_t rows = 11, heads = 3, row_stride = heads * head_dim + 7, pairs = head_dim / 2;
    const auto x = test::random_floats(static_cast<std::size_t>(rows * row_stride), 51, -2.f, 2.f);
    const auto angle = test::random_floats(static_cast<std::size_t>(rows * pairs), 52, -10.f, 10.f);
    std::vector<float> c(angle.size()), s(angle.size());
    for (std::size_t i = 0; i < angle.size(); ++i) {
      c[i] = std::cos(angle[i]);
      s[i] = std::sin(angle[i]);
    }
    std::vector<double> ref(x.begin(), x.end());
    for (std::int64_t r = 0; r < rows; ++r)
      for (std::int64_t h = 0; h < heads; ++h)
        for (std::int64_t j = 0; j < pairs; ++j) {
          const std::int64_t o = r * row_stride + h * head_dim + 2 * j;
          const double cj = c[r * pairs + j], sj = s[r * pairs + j];
          ref[o] = cj * x[o] - sj * x[o + 1];
          ref[o + 1] = sj * x[o] + cj * x[o + 1];
        }
    auto y = x;
    cpu::apply_rope(ctx, y.data(), rows, row_stride, heads, head_dim, c.data(), s.data());
    CAPTURE(head_dim);
    CHECK(test::rel_max(y, ref) <= 1e-6);
    for (std::int64_t r = 0; r < rows; ++r)
      for (std::int64_t i = heads * head_dim; i < row_stride; ++i) CHECK(y[r * row_stride + i] == x[r * row_stride + i]);
  }
}

TEST_CASE("apply_rope with the identity table leaves x unchanged, odd head_dim is an error") {
  cpu::Context ctx;
  const std::int64_t rows = 3, heads = 2, head_dim = 24;
  const auto x = test::random_floats(static_cast<std::size_t>(rows * heads * head_dim), 53);
  std::vector<float> c(static_cast<std::size_t>(rows * head_dim / 2), 1.f), s(c.size(), 0.f);
  auto y = x;
  cpu::apply_rope(ctx, y.data(), rows, heads * head_dim, heads, head_dim, c.data(), s.data());
  CHECK(y == x);
  CHECK_THROWS_WITH_AS(cpu::apply_rope(ctx, y.data(), rows, heads * 5, heads, 5, c.data(), s.data()),
                       doctest::Contains("even"), Error);
}
