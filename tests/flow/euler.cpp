// The Euler sampler against exact float64 recurrences: x <- x + fp32(t_{i+1} - t_i)·v(x, t_i)
// for v = const (the sum of the rounded steps) and v = -x (a product), on a shifted grid; the
// velocity is called exactly N times at t_0..t_{N-1} (never at t = 1), in order.
#include <doctest/doctest.h>

#include <cmath>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/flow/euler.hpp"
#include "epona/flow/schedule.hpp"

using namespace epona;

TEST_CASE("Euler: calls, step sizes and linear velocities") {
  cpu::Context ctx(1);
  const auto grid = flow::get_schedule(20, 512);
  const flow::RectifiedFlowEuler<Cpu> euler(grid);
  CHECK(euler.steps() == 20);
  for (std::int64_t i = 0; i < 20; ++i)
    CHECK(euler.step_size(i) == static_cast<float>(double(grid[i + 1]) - double(grid[i])));

  Tensor<float, Cpu> x = Tensor<float, Cpu>::full({3, 5}, 0.5f), v({3, 5});
  std::vector<float> seen;
  euler.sample(ctx, x, v, [&](std::int64_t i, float t, const Tensor<float, Cpu>&, Tensor<float, Cpu>& out) {
    CHECK(i == static_cast<std::int64_t>(seen.size()));
    seen.push_back(t);
    for (std::int64_t k = 0; k < out.numel(); ++k) out.data()[k] = 2.0f;
  });
  REQUIRE(seen.size() == 20);
  for (std::size_t i = 0; i < seen.size(); ++i) CHECK(seen[i] == grid[i]);  // never t = 1
  double expected = 0.5;
  for (std::int64_t i = 0; i < 20; ++i) expected = float(expected + float(euler.step_size(i) * 2.0f));
  for (std::int64_t k = 0; k < x.numel(); ++k) CHECK(x.data()[k] == float(expected));

  // v = -x: x_N = x_0 · Π (1 - Δt_i), to float rounding.
  Tensor<float, Cpu> y = Tensor<float, Cpu>::full({4}, 3.0f), w({4});
  euler.sample(ctx, y, w, [](std::int64_t, float, const Tensor<float, Cpu>& s, Tensor<float, Cpu>& out) {
    for (std::int64_t k = 0; k < s.numel(); ++k) out.data()[k] = -s.data()[k];
  });
  double prod = 3.0;
  for (std::int64_t i = 0; i < 20; ++i) prod *= 1.0 - double(euler.step_size(i));
  CHECK(y.data()[0] == doctest::Approx(prod).epsilon(1e-6));
}

TEST_CASE("Euler refuses a grid without steps and mismatched buffers") {
  CHECK_THROWS_AS(flow::RectifiedFlowEuler<Cpu>(std::vector<float>{0.0f}), Error);
  cpu::Context ctx(1);
  const flow::RectifiedFlowEuler<Cpu> euler(flow::get_schedule(2, 15));
  Tensor<float, Cpu> x({4}), v({5});
  CHECK_THROWS_AS(euler.sample(ctx, x, v, [](auto, auto, const auto&, auto&) {}), Error);
}
