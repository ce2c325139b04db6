// Tests for epona/cpu/activation.hpp: GELU (erf and tanh forms) and SiLU against float64
// formulas, on sizes that exercise the SIMD tails and the multi-threaded path.
// Tolerance: max |got − ref| / max |ref| <= 1e-6, and per element <= 4e-7·(|ref| + 1) (the
// float cancellation in 1 + erf(x) for very negative x, which torch has too, bounds the floor).
#include <doctest/doctest.h>

#include <cmath>
#include <functional>

#include "epona/cpu/activation.hpp"
#include "testing.hpp"

using namespace epona;

namespace {
double gelu_erf_ref(double x) { return 0.5 * x * (1.0 + std::erf(x / std::sqrt(2.0))); }
double gelu_tanh_ref(double x) {
  return 0.5 * x * (1.0 + std::tanh(std::sqrt(2.0 / M_PI) * (x + 0.044715 * x * x * x)));
}
double silu_ref(double x) { return x / (1.0 + std::exp(-x)); }

void check_activation(void (*kernel)(cpu::Context&, float*, std::int64_t), double (*ref)(double)) {
  cpu::Context ctx;
  std::vector<std::int64_t> sizes = test::odd_sizes();
  sizes.push_back(70001);  // large enough for the threaded path
  for (auto n : sizes) {
    auto x = test::random_floats(static_cast<std::size_t>(n), 7 + static_cast<std::uint32_t>(n), -8.f, 8.f);
    if (n > 8) {  // edge values: zero, tiny, far tails
      x[0] = 0.f; x[1] = 1e-20f; x[2] = -30.f; x[3] = 30.f; x[4] = -90.f; x[5] = 90.f; x[6] = -1e-3f;
    }
    std::vector<double> r(x.size());
    for (std::size_t i = 0; i < x.size(); ++i) r[i] = ref(x[i]);
    auto y = x;
    kernel(ctx, y.data(), n);
    CAPTURE(n);
    CHECK(test::rel_max(y, r) <= 1e-6);
    for (std::size_t i = 0; i < x.size(); ++i) {
      CAPTURE(x[i]);
      REQUIRE(std::abs(y[i] - r[i]) <= 4e-7 * (std::abs(r[i]) + 1.0));
    }
  }
}
}  // namespace

TEST_CASE("gelu_erf matches 0.5·x·(1 + erf(x/√2))") { check_activation(cpu::gelu_erf, gelu_erf_ref); }
TEST_CASE("gelu_tanh matches the tanh approximation") { check_activation(cpu::gelu_tanh, gelu_tanh_ref); }
TEST_CASE("silu matches x·sigmoid(x)") { check_activation(cpu::silu, silu_ref); }

TEST_CASE("silu_to writes a separate buffer and leaves the input") {
  cpu::Context ctx;
  for (auto n : test::odd_sizes()) {
    const auto x = test::random_floats(static_cast<std::size_t>(n), 3, -5.f, 5.f);
    std::vector<float> y(x.size(), -1.f);
    cpu::silu_to(ctx, x.data(), y.data(), n);
    auto xc = x;
    cpu::silu(ctx, xc.data(), n);
    CHECK(y == xc);  // same code path, bit-identical
    std::vector<double> r(x.size());
    for (std::size_t i = 0; i < x.size(); ++i) r[i] = silu_ref(x[i]);
    CHECK(test::rel_max(y, r) <= 1e-6);
  }
}

TEST_CASE("activations of large-magnitude inputs are finite (no NaN from overflow)") {
  cpu::Context ctx;
  std::vector<float> x{-1e30f, -1e6f, -200.f, 200.f, 1e6f, 1e30f};
  for (auto kernel : {cpu::gelu_erf, cpu::gelu_tanh, cpu::silu}) {
    auto y = x;
    kernel(ctx, y.data(), static_cast<std::int64_t>(y.size()));
    for (std::size_t i = 0; i < y.size(); ++i) {
      CAPTURE(x[i]);
      CHECK(std::isfinite(y[i]));
      if (x[i] > 0) CHECK(y[i] == doctest::Approx(x[i]).epsilon(1e-6));
      else CHECK(std::abs(y[i]) <= 1e-30f);
    }
  }
}
