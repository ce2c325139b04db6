// Tests for epona/cpu/softmax.hpp: the row softmax against a float64 loop on odd widths, with
// −inf entries and fully masked rows (zeros, not NaN).
// Tolerance: max |got − ref| / max |ref| <= 1e-6, and per probability 1e-6 relative.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>

#include "epona/cpu/softmax.hpp"
#include "testing.hpp"

using namespace epona;

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
    CHECK(test::rel_max(x, ref) <= 1e-6);
    for (std::int64_t r = 0; r < rows; ++r)
      for (std::int64_t i = 0; i < n; ++i) {
        CHECK(std::isfinite(x[r * n + i]));
        // Relative accuracy per element on the probabilities that matter.
        if (ref[r * n + i] > 1e-30) CHECK(std::abs(x[r * n + i] - ref[r * n + i]) <= 1e-6 * ref[r * n + i] + 1e-12);
      }
  }
}
