// Tests for epona/cpu/elementwise.hpp: residual adds, the gated residual and row broadcasts
// against float64 loops on odd sizes.
// Tolerance: max |got − ref| / max |ref| <= 1e-6.
#include <doctest/doctest.h>

#include <cmath>

#include "epona/cpu/elementwise.hpp"
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
      CHECK(test::rel_max(a, r_add) <= 1e-6);
      CHECK(test::rel_max(b, r_gate) <= 1e-6);
      CHECK(test::rel_max(c, r_row) <= 1e-6);
    }
  }
  // Threaded path of add_inplace.
  const std::int64_t n = 100003;
  auto x = test::random_floats(n, 64);
  const auto y = test::random_floats(n, 65);
  std::vector<double> ref(x.size());
  for (std::int64_t i = 0; i < n; ++i) ref[i] = double(x[i]) + y[i];
  cpu::add_inplace(ctx, x.data(), y.data(), n);
  CHECK(test::rel_max(x, ref) <= 1e-6);
}
