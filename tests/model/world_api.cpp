// The WorldModel API on the golden weights: plan / predict_next reproduce the golden rollout's
// first step through their own paths (planner only; VisDiT conditioned on a given action),
// seeded noise follows step_eval's draw order, batch items are independent, and bad input
// (non-finite values, wrong frame counts or shapes, steps <= 0, short noise) is refused with an
// epona::Error naming the problem.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <string>

#include "epona/core/rng.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "../error_text.hpp"
#include "golden_world_model.hpp"

using namespace epona;
using epona::test::golden_world_model;
using epona::test::rel_max;
using epona::test::world_golden;

namespace {

using epona::test::golden_history;

// Step 0 of a supplied per-step noise tensor as a one-step (1, ...) tensor.
Tensor<float, Cpu> step0(const std::string& name) {
  const auto t = world_golden().tensor(name);
  Shape s = t.shape();
  s[0] = 1;
  return t.slice(0, 1).clone().reshape(s);
}

using epona::test::contains;
using epona::test::error_of;

}  // namespace

TEST_CASE("plan() reproduces the golden first planned trajectory") {
  SampleOptions opt;
  opt.noise = NoiseSource::supplied(step0("rollout.noise_traj"), {});
  const auto traj = golden_world_model().plan(golden_history(), opt);
  const auto golden = world_golden().tensor("rollout.predict_traj")[0];
  const double rel = rel_max(traj, golden);
  MESSAGE("plan vs rollout.predict_traj[0]: rel ", rel);
  CHECK(rel <= 1e-4);
}

TEST_CASE("predict_next() with the action given equals the self-predicted step") {
  // The golden step 0 used its own first waypoint as the action: give that waypoint explicitly.
  const auto golden_traj = world_golden().tensor("rollout.predict_traj")[0];  // (B, traj_len, 3)
  const std::int64_t B = golden_traj.size(0);
  NextAction action{Tensor<float, Cpu>({B, 1, 2}), Tensor<float, Cpu>({B, 1, 1})};
  for (std::int64_t b = 0; b < B; ++b) {
    action.rel_pose.at(b, 0, 0) = golden_traj.at(b, 0, 0);
    action.rel_pose.at(b, 0, 1) = golden_traj.at(b, 0, 1);
    action.rel_yaw.at(b, 0, 0) = golden_traj.at(b, 0, 2);
  }
  SampleOptions opt;
  opt.noise = NoiseSource::supplied({}, step0("rollout.noise_img"));  // a given action draws no trajectory noise
  const auto r = golden_world_model().predict_next(golden_history(), action, opt);
  CHECK(r.trajectory.empty());
  const auto golden = world_golden().tensor("rollout.predict_latents")[0];
  const double rel = rel_max(r.latent, golden.reshape(r.latent.shape()));
  MESSAGE("predict_next(action) vs rollout.predict_latents[0]: rel ", rel);
  CHECK(rel <= 1e-4);
}

TEST_CASE("seeded noise: trajectory noise then latent noise from one torch generator") {
  const auto& w = world_golden().configs.world;
  const auto h = golden_history();
  const std::int64_t B = h.latents.size(0);
  SampleOptions seeded;
  seeded.seed = 1234;
  seeded.steps = 3;
  const auto a = golden_world_model().predict_next(h, std::nullopt, seeded);
  const auto b = golden_world_model().predict_next(h, std::nullopt, seeded);
  CHECK(rel_max(a.latent, b.latent) == 0);
  TorchGenerator gen(1234);
  auto traj_noise = gen.randn({1, B, w.traj_len, 3});
  auto latent_noise = gen.randn({1, B, w.img_tokens(), w.token_dim()});
  SampleOptions supplied;
  supplied.steps = 3;
  supplied.noise = NoiseSource::supplied(traj_noise, latent_noise);
  const auto c = golden_world_model().predict_next(h, std::nullopt, supplied);
  CHECK(rel_max(a.trajectory, c.trajectory) == 0);
  CHECK(rel_max(a.latent, c.latent) == 0);
}

TEST_CASE("batch items are independent") {
  const auto& w = world_golden().configs.world;
  const auto h1 = golden_history();
  // Item 0 is the golden window, item 1 a different one (other latents and actions).
  History h2{Tensor<float, Cpu>({2, w.condition_frames, w.img_tokens(), w.token_dim()}),
             Tensor<float, Cpu>({2, w.condition_frames, 2}), Tensor<float, Cpu>({2, w.condition_frames, 1})};
  const auto fill = [](Tensor<float, Cpu>& two, const Tensor<float, Cpu>& one, float scale) {
    const std::int64_t n = one.numel();
    std::copy_n(one.data(), n, two.data());
    for (std::int64_t i = 0; i < n; ++i) two.data()[n + i] = one.data()[n - 1 - i] * scale;
  };
  fill(h2.latents, h1.latents, 0.5f);
  fill(h2.rel_pose, h1.rel_pose, 1.5f);
  fill(h2.rel_yaw, h1.rel_yaw, -1.0f);
  TorchGenerator gen(7);
  auto traj_noise = gen.randn({1, 2, w.traj_len, 3});
  auto latent_noise = gen.randn({1, 2, w.img_tokens(), w.token_dim()});
  SampleOptions o2, o1;
  o2.steps = o1.steps = 4;
  o2.noise = NoiseSource::supplied(traj_noise, latent_noise);
  o1.noise = NoiseSource::supplied(traj_noise.reshape({2, w.traj_len, 3}).slice(0, 1).clone().reshape({1, 1, w.traj_len, 3}),
                                   latent_noise.reshape({2, w.img_tokens(), w.token_dim()}).slice(0, 1).clone().reshape(
                                       {1, 1, w.img_tokens(), w.token_dim()}));
  const auto two = golden_world_model().predict_next(h2, std::nullopt, o2);
  const auto one = golden_world_model().predict_next(h1, std::nullopt, o1);
  // Equal up to GEMM accumulation order (batched projections see more rows).
  const double rel_traj = rel_max(two.trajectory.slice(0, 1), one.trajectory);
  const double rel_latent = rel_max(two.latent.slice(0, 1), one.latent);
  MESSAGE("batch of 2 vs 1, item 0: trajectory rel ", rel_traj, ", latent rel ", rel_latent);
  CHECK(rel_traj <= 1e-5);
  CHECK(rel_latent <= 1e-5);
  const double rel_other = rel_max(two.latent.slice(1, 2), one.latent);  // infinite on a NaN or Inf
  CHECK(std::isfinite(rel_other));
  CHECK(rel_other > 0);
}

TEST_CASE("bad input is refused before any work, with the problem named") {
  const auto& w = world_golden().configs.world;
  auto& m = golden_world_model();
  const auto good = golden_history();
  SampleOptions opt;
  opt.steps = 2;

  auto nan_latents = good;
  nan_latents.latents = good.latents.clone();
  nan_latents.latents.data()[5] = std::numeric_limits<float>::quiet_NaN();
  CHECK(contains(error_of([&] { (void)m.plan(nan_latents, opt); }), "history latents has a non-finite value"));

  auto inf_pose = good;
  inf_pose.rel_pose = good.rel_pose.clone();
  inf_pose.rel_pose.data()[1] = std::numeric_limits<float>::infinity();
  CHECK(contains(error_of([&] { (void)m.predict_next(inf_pose, std::nullopt, opt); }), "history rel_pose"));

  History short_window{Tensor<float, Cpu>::zeros({1, w.condition_frames - 1, w.img_tokens(), w.token_dim()}),
                       Tensor<float, Cpu>::zeros({1, w.condition_frames - 1, 2}),
                       Tensor<float, Cpu>::zeros({1, w.condition_frames - 1, 1})};
  CHECK(contains(error_of([&] { (void)m.plan(short_window, opt); }), "latent frames; the model needs"));

  auto wrong_tokens = good;
  wrong_tokens.latents = Tensor<float, Cpu>::zeros({1, w.condition_frames, w.img_tokens() + 1, w.token_dim()});
  CHECK(contains(error_of([&] { (void)m.plan(wrong_tokens, opt); }), "history latents: expected shape"));

  auto wrong_yaw = good;
  wrong_yaw.rel_yaw = Tensor<float, Cpu>::zeros({1, w.condition_frames, 2});
  CHECK(contains(error_of([&] { (void)m.plan(wrong_yaw, opt); }), "history rel_yaw"));

  for (const std::int64_t steps : {std::int64_t{0}, std::int64_t{-3}, std::int64_t{1} << 40}) {
    SampleOptions bad;  // 2^40 steps would be a 4 TB schedule: refused before anything is allocated
    bad.steps = steps;
    CHECK(contains(error_of([&] { (void)m.plan(good, bad); }), "sampling steps must be in [1, 100000]"));
  }

  NextAction nan_action{Tensor<float, Cpu>::zeros({1, 1, 2}), Tensor<float, Cpu>::full({1, 1, 1}, NAN)};
  CHECK(contains(error_of([&] { (void)m.predict_next(good, nan_action, opt); }), "next action rel_yaw"));

  SampleOptions wrong_noise = opt;
  wrong_noise.noise = NoiseSource::supplied(Tensor<float, Cpu>::zeros({1, 1, w.traj_len + 1, 3}), {});
  CHECK(contains(error_of([&] { (void)m.plan(good, wrong_noise); }), "trajectory noise has shape"));

  RolloutOptions ro;
  ro.frames = 3;
  ro.sample.steps = 2;
  ro.sample.noise = NoiseSource::supplied(Tensor<float, Cpu>::zeros({2, 1, w.traj_len, 3}),
                                          Tensor<float, Cpu>::zeros({2, 1, w.img_tokens(), w.token_dim()}));
  CHECK(contains(error_of([&] { (void)rollout(m, good, ro); }), "noise for 2 step(s) supplied, 3 needed"));
  ro.frames = 0;
  CHECK(contains(error_of([&] { (void)rollout(m, good, ro); }), "rollout frames must be in [1, 1000000]"));
  ro.frames = std::int64_t{1} << 40;
  CHECK(contains(error_of([&] { (void)rollout(m, good, ro); }), "rollout frames must be in [1, 1000000]"));
}
