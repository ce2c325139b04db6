// get_schedule against its closed form t_i = u/(u + e^mu (1 - u)), u = i/N, evaluated in
// float64 (the spec bounds the fp32 difference by 1.3e-7), for many (N, L); endpoints exact,
// strictly increasing, mu through (256, 0.5) and (4096, 1.15); bad arguments refused. The
// bit-exact comparison with the official grids is in tests/model/world_parity.cpp.
#include <doctest/doctest.h>

#include <cmath>

#include "epona/flow/schedule.hpp"

using namespace epona;

TEST_CASE("schedule matches the closed form and is a 0 -> 1 increasing grid") {
  const flow::ScheduleShift shift;
  CHECK(shift.mu(256) == doctest::Approx(0.5).epsilon(1e-15));
  CHECK(shift.mu(4096) == doctest::Approx(1.15).epsilon(1e-15));
  double worst = 0;
  for (const std::int64_t n : {1, 2, 3, 10, 50, 100, 101, 1000})
    for (const std::int64_t len : {1, 8, 15, 128, 512, 4096, 100000}) {
      const auto t = flow::get_schedule(n, len);
      REQUIRE(t.size() == static_cast<std::size_t>(n + 1));
      CHECK(t.front() == 0.0f);
      CHECK(t.back() == 1.0f);
      const double e_mu = std::exp(shift.mu(len));
      for (std::int64_t i = 0; i <= n; ++i) {
        const double u = double(i) / double(n);
        worst = std::max(worst, std::abs(t[i] - u / (u + e_mu * (1 - u))));
        // Strictly increasing at sizes the model uses; at absurd lengths the fp32 1 - sigma
        // rounds the first steps to 0 (as the official tensors do), so only non-decreasing.
        if (i) CHECK((len <= 4096 ? t[i] > t[i - 1] : t[i] >= t[i - 1]));
      }
    }
  MESSAGE("largest |fp32 grid - closed form| ", worst);
  CHECK(worst <= 1.3e-7);
}

TEST_CASE("schedule arguments are checked") {
  CHECK_THROWS_WITH_AS(flow::get_schedule(0, 512), doctest::Contains("must be in [1, 100000]"), Error);
  CHECK_THROWS_WITH_AS(flow::get_schedule(-5, 512), doctest::Contains("must be in [1, 100000]"), Error);
  // 2^40 steps: refused before a 4 TB vector is asked for (std::bad_alloc otherwise)
  CHECK_THROWS_WITH_AS(flow::get_schedule(std::int64_t{1} << 40, 512), doctest::Contains("must be in [1, 100000]"), Error);
  CHECK(flow::get_schedule(100000, 512).size() == 100001);
  CHECK_THROWS_AS(flow::get_schedule(10, 0), Error);
}
