// WorldModel::plan_hypotheses on the golden weights: hypothesis k is the plan of its seed alone
// (the batch of K shares one MST run), K = 1 is plan() itself, and bad requests (K out of range,
// a batch of scenes, supplied noise) are refused with an epona::Error naming the problem.
#include <doctest/doctest.h>

#include <string>

#include "epona/model/world_model.hpp"
#include "../error_text.hpp"
#include "golden_world_model.hpp"

using namespace epona;
using epona::test::golden_world_model;
using epona::test::rel_max;

namespace {

// Scene 0 of the golden window, alone (Bt = 1).
History one_scene() {
  const History h = epona::test::golden_history();
  const auto first = [](const Tensor<float, Cpu>& t) {
    Shape s = t.shape();
    s[0] = 1;
    return t.slice(0, 1).clone().reshape(s);
  };
  return {first(h.latents), first(h.rel_pose), first(h.rel_yaw)};
}

using epona::test::contains;
using epona::test::error_of;

}  // namespace

TEST_CASE("hypothesis k is the plan of seed + k*step alone") {
  const History h = one_scene();
  SampleOptions opt;
  opt.steps = 6;
  opt.seed = 11;
  const std::int64_t K = 5;
  const auto fan = golden_world_model().plan_hypotheses(h, K, opt);
  REQUIRE(fan.shape() == Shape{K, golden_world_model().config().traj_len, 3});
  double worst = 0;
  for (std::int64_t k = 0; k < K; ++k) {
    SampleOptions alone = opt;
    alone.seed = WorldModel<Cpu, float>::hypothesis_seed(opt.seed, k);
    const auto plan = golden_world_model().plan(h, alone);  // (1, traj_len, 3)
    worst = std::max(worst, rel_max(fan.slice(k, k + 1), plan));
  }
  MESSAGE("hypotheses vs plans alone: worst rel ", worst);
  CHECK(worst <= 1e-6);  // the batch of K only adds GEMM rows
  // Distinct seeds give distinct plans.
  CHECK(rel_max(fan.slice(1, 2), fan.slice(0, 1)) > 1e-3);
  CHECK(WorldModel<Cpu, float>::hypothesis_seed(11, 0) == 11);
}

TEST_CASE("one hypothesis is plan()") {
  const History h = one_scene();
  SampleOptions opt;
  opt.steps = 4;
  opt.seed = 3;
  CHECK(rel_max(golden_world_model().plan_hypotheses(h, 1, opt), golden_world_model().plan(h, opt)) == 0.0);
}

TEST_CASE("plan_hypotheses refuses what it cannot do, naming it") {
  const History h = one_scene();
  SampleOptions opt;
  opt.steps = 2;
  CHECK(contains(error_of([&] { golden_world_model().plan_hypotheses(h, 0, opt); }), "number of plan hypotheses must be in [1, "));
  CHECK(contains(error_of([&] { golden_world_model().plan_hypotheses(h, constants::max_hypotheses + 1, opt); }), "hypotheses"));
  SampleOptions supplied = opt;
  supplied.noise = NoiseSource::seeded(1);
  CHECK(contains(error_of([&] { golden_world_model().plan_hypotheses(h, 2, supplied); }), "takes no supplied noise"));
  History two = h;
  const auto twice = [](const Tensor<float, Cpu>& t) {
    Shape s = t.shape();
    s[0] = 2;
    Tensor<float, Cpu> out(s);
    std::copy_n(t.data(), t.numel(), out.data());
    std::copy_n(t.data(), t.numel(), out.data() + t.numel());
    return out;
  };
  two = {twice(h.latents), twice(h.rel_pose), twice(h.rel_yaw)};
  CHECK(contains(error_of([&] { golden_world_model().plan_hypotheses(two, 2, opt); }), "plans one scene; the window holds 2"));
  History bad = h;
  bad.rel_yaw = h.rel_yaw.clone();
  bad.rel_yaw.data()[0] = std::numeric_limits<float>::quiet_NaN();
  CHECK(contains(error_of([&] { golden_world_model().plan_hypotheses(bad, 2, opt); }), "non-finite"));
}
