// model::choose_plan against a plain float64 reference: the medoid (least summed mean waypoint
// distance to the others, ties to the lower index), the waypoint-wise mean, and the spread (RMS
// distance from the mean position); K = 1, and bad shapes or values refused.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "epona/model/plan_choice.hpp"

using namespace epona;
using model::PlanChoice;

namespace {

Tensor<float> random_fan(std::int64_t K, std::int64_t W, unsigned seed) {
  std::mt19937 gen(seed);
  std::normal_distribution<float> n(0.f, 1.f);
  Tensor<float> t({K, W, 3});
  for (std::int64_t k = 0; k < K; ++k)
    for (std::int64_t w = 0; w < W; ++w) {
      t.at(k, w, 0) = 2.f * float(w + 1) + n(gen);
      t.at(k, w, 1) = 0.3f * n(gen) * float(w);
      t.at(k, w, 2) = n(gen);
    }
  return t;
}

std::int64_t reference_medoid(const Tensor<float>& t) {
  const std::int64_t K = t.size(0), W = t.size(1);
  std::int64_t best = -1;
  double best_total = 0;
  for (std::int64_t a = 0; a < K; ++a) {
    double total = 0;
    for (std::int64_t b = 0; b < K; ++b) {
      double d = 0;
      for (std::int64_t w = 0; w < W; ++w) {
        const double dx = double(t.at(a, w, 0)) - double(t.at(b, w, 0)), dy = double(t.at(a, w, 1)) - double(t.at(b, w, 1));
        d += std::sqrt(dx * dx + dy * dy);
      }
      total += d / double(W);
    }
    if (best < 0 || total < best_total - 1e-12) best = a, best_total = total;
  }
  return best;
}

}  // namespace

TEST_CASE("medoid, mean and spread match a float64 reference") {
  for (unsigned seed : {1u, 2u, 3u}) {
    const auto t = random_fan(9, 15, seed);
    const auto medoid = model::choose_plan(t, PlanChoice::medoid);
    REQUIRE(medoid.chosen_index.has_value());
    CHECK(*medoid.chosen_index == reference_medoid(t));
    for (std::int64_t i = 0; i < 45; ++i) CHECK(medoid.chosen.data()[i] == t[*medoid.chosen_index].data()[i]);
    const auto mean = model::choose_plan(t, PlanChoice::mean);
    CHECK(!mean.chosen_index);
    for (std::int64_t w = 0; w < 15; ++w) {
      double m[3] = {0, 0, 0};
      for (std::int64_t k = 0; k < 9; ++k)
        for (int c = 0; c < 3; ++c) m[c] += t.at(k, w, c) / 9.0;
      for (int c = 0; c < 3; ++c) CHECK(mean.chosen.at(w, c) == doctest::Approx(m[c]).epsilon(1e-6));
      double sq = 0;
      for (std::int64_t k = 0; k < 9; ++k)
        sq += std::pow(t.at(k, w, 0) - m[0], 2) + std::pow(t.at(k, w, 1) - m[1], 2);
      CHECK(mean.spread_m[w] == doctest::Approx(std::sqrt(sq / 9.0)).epsilon(1e-9));
      CHECK(medoid.spread_m[w] == mean.spread_m[w]);
    }
  }
}

TEST_CASE("the medoid resists an outlier; ties go to the lower index") {
  Tensor<float> t({3, 2, 3});
  for (std::int64_t k = 0; k < 3; ++k)
    for (std::int64_t w = 0; w < 2; ++w) t.at(k, w, 0) = float(w + 1), t.at(k, w, 1) = 0, t.at(k, w, 2) = 0;
  t.at(2, 1, 1) = 50.f;  // hypothesis 2 swerves far away
  const auto fan = model::choose_plan(t, PlanChoice::medoid);
  CHECK(*fan.chosen_index == 0);  // 0 and 1 tie
  CHECK(model::choose_plan(t, PlanChoice::mean).chosen.at(1, 1) == doctest::Approx(50.0 / 3.0));
}

TEST_CASE("one hypothesis is its own choice with no spread") {
  const auto t = random_fan(1, 15, 4);
  for (auto rule : {PlanChoice::medoid, PlanChoice::mean}) {
    const auto fan = model::choose_plan(t, rule);
    for (std::int64_t i = 0; i < 45; ++i) CHECK(fan.chosen.data()[i] == doctest::Approx(t.data()[i]));
    for (double s : fan.spread_m) CHECK(s == 0.0);
  }
}

TEST_CASE("bad fans are refused") {
  CHECK_THROWS_WITH_AS(model::choose_plan(Tensor<float>({2, 15}), PlanChoice::medoid),
                       doctest::Contains("plan hypotheses must be (K, W, 3)"), Error);
  CHECK_THROWS_AS(model::choose_plan(Tensor<float>({0, 15, 3}), PlanChoice::mean), Error);
  auto t = random_fan(3, 4, 5);
  t.at(1, 2, 0) = std::numeric_limits<float>::infinity();
  CHECK_THROWS_WITH_AS(model::choose_plan(t, PlanChoice::medoid), doctest::Contains("plan hypothesis 1 has a non-finite"), Error);
}
