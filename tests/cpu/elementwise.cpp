// Tests for epona/cpu/elementwise.hpp and epona/cpu/softmax.hpp: residual adds, the gated
// residual, row broadcasts and the row softmax, against float64 loops on odd sizes.
// Tolerance: max |got − ref| / max |ref| <= 1e-6.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>

#include "epona/cpu/elementwise.hpp"
#include "epona/cpu/softmax.hpp"
#include "testing.hpp"

using namespace epona;

TEST_CASE("add_inplace, add_gated and add_row_broadcast") {
  cpu::Context ctx;
  for (auto n : test::odd_sizes()) {
    for (std::int64_t rows : {1, 3, 40}) {
      const auto x = test::random_floats(static_cast<std::size_t>(rows * n), 61);
      const auto y = test::random_floats(static_cast<std::size_t>(rows * n), 62);
      const auto g = test::random_floats(static_cast<std::size_t>(n), 63);
      std::vector<double> r_add(x.size()), r_gate(x.size()), r_row(x.size());
      for (std::int64_t r = 0; r < rows; ++r)
        for (std::int64_t i = 0; i < n; ++i) {
          const auto k = r * n + i;
          r_add[k] = double(x[k]) + y[k];
          r_gate[k] = x[k] + double(g[i]) * y[k];
          r_row[k] = double(x[k]) + g[i];
        }
      auto a = x, b = x, c = x;
      cpu::add_inplace(ctx, a.data(), y.data(), rows * n);
      cpu::add_gated(ctx, b.data(), y.data(), g.data(), rows, n);
      cpu::add_row_broadcast(ctx, c.data(), g.data(), rows, n);
      CAPTURE(n);
      CAPTURE(rows);
      CHECK(test::max_rel_error(a, r_add) <= 1e-6);
      CHECK(test::max_rel_error(b, r_gate) <= 1e-6);
      CHECK(test::max_rel_error(c, r_row) <= 1e-6);
    }
  }
  // Threaded path of add_inplace.
  const std::int64_t n = 100003;
  auto x = test::random_floats(n, 64);
  const auto y = test::random_floats(n, 65);
  std::vector<double> ref(x.size());
  for (std::int64_t i = 0; i < n; ++i) ref[i] = double(x[i]) + y[i];
  cpu::add_inplace(ctx, x.data(), y.data(), n);
  CHECK(test::max_rel_error(x, ref) <= 1e-6);
}

TEST_CASE("softmax_rows: exp(x − max) / sum, masked entries and fully masked rows") {
  cpu::Context ctx;
  constexpr float ninf = -std::numeric_limits<float>::infinity();
  for (auto n : test::odd_sizes()) {
    const std::int64_t rows = 4;
    auto x = test::random_floats(static_cast<std::size_t>(rows * n), 71, -20.f, 20.f);
    for (std::int64_t i = 0; i < n; i += 3) x[n + i] = ninf;  // row 1: partly masked
    for (std::int64_t i = 0; i < n; ++i) x[2 * n + i] = ninf;  // row 2: fully masked
    std::vector<double> ref(x.size());
    for (std::int64_t r = 0; r < rows; ++r) {
      double mx = -INFINITY, s = 0;
      for (std::int64_t i = 0; i < n; ++i) mx = std::max(mx, double(x[r * n + i]));
      for (std::int64_t i = 0; i < n; ++i) s += mx == -INFINITY ? 0 : std::exp(x[r * n + i] - mx);
      for (std::int64_t i = 0; i < n; ++i) ref[r * n + i] = s > 0 ? std::exp(x[r * n + i] - mx) / s : 0.0;
    }
    cpu::softmax_rows(ctx, x.data(), rows, n);
    CAPTURE(n);
    CHECK(test::max_rel_error(x, ref) <= 1e-6);
    for (std::int64_t r = 0; r < rows; ++r)
      for (std::int64_t i = 0; i < n; ++i) {
        CHECK(std::isfinite(x[r * n + i]));
        // Relative accuracy per element on the probabilities that matter.
        if (ref[r * n + i] > 1e-30) CHECK(std::abs(x[r * n + i] - ref[r * n + i]) <= 1e-6 * ref[r * n + i] + 1e-12);
      }
  }
}
