// Per-item noise (SampleOptions::item_seeds, NoiseSource::seeded_per_item): item b of a batch
// draws what seeded(seeds[b]) draws for a batch of 1, so an item's result does not depend on the
// batch it runs in. A batch of 3 windows against each window alone, through predict_next and a
// 2-frame rollout, on the golden weights; a seed count that is not the batch is refused.
#include <doctest/doctest.h>

#include <algorithm>
#include <cstdint>
#include <vector>

#include "epona/core/rng.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "../error_text.hpp"
#include "golden_world_model.hpp"

using namespace epona;
using epona::test::golden_world_model;
using epona::test::contains;
using epona::test::error_of;
using epona::test::rel_max;

namespace {

const std::vector<std::uint64_t> kSeeds{11, 2026, 0x9E3779B9u};
constexpr double kBatchTolerance = 1e-6;  // relative; batch and single runs differ only in GEMM row counts

// Item b of the batch is the golden window with its values reversed and scaled by a per-item
// factor (item 0 the golden window itself), so the three scenes differ.
Tensor<float, Cpu> stack_variants(const Tensor<float, Cpu>& one, std::int64_t count, float step) {
  Shape shape = one.shape();
  shape[0] = count;
  Tensor<float, Cpu> out(shape);
  const std::int64_t n = one.numel();
  for (std::int64_t b = 0; b < count; ++b)
    for (std::int64_t i = 0; i < n; ++i)
      out.data()[b * n + i] = b == 0 ? one.data()[i] : one.data()[n - 1 - i] * (1.0f + step * static_cast<float>(b));
  return out;
}

History three_windows() {
  const History golden = epona::test::golden_history();
  REQUIRE(golden.latents.size(0) == 1);
  const auto count = static_cast<std::int64_t>(kSeeds.size());
  return {stack_variants(golden.latents, count, -0.25f), stack_variants(golden.rel_pose, count, 0.5f),
          stack_variants(golden.rel_yaw, count, -1.5f)};
}

History item_of(const History& h, std::int64_t b) {
  return {h.latents.slice(b, b + 1).clone(), h.rel_pose.slice(b, b + 1).clone(), h.rel_yaw.slice(b, b + 1).clone()};
}

}  // namespace

TEST_CASE("per-item seeds: the noise of item b is seeded(seeds[b])'s for a batch of 1") {
  const auto& w = epona::test::world_golden().world();
  auto batch = NoiseSource::seeded_per_item(kSeeds);
  const auto count = static_cast<std::int64_t>(kSeeds.size());
  const auto traj = batch.trajectory({count, w.traj_len, 3});
  const auto latent = batch.latent({count, w.img_tokens(), w.token_dim()});
  for (std::int64_t b = 0; b < count; ++b) {
    auto alone = NoiseSource::seeded(kSeeds[static_cast<std::size_t>(b)]);
    CHECK(rel_max(traj[b], alone.trajectory({1, w.traj_len, 3})[0]) == 0);
    CHECK(rel_max(latent[b], alone.latent({1, w.img_tokens(), w.token_dim()})[0]) == 0);
  }
}

TEST_CASE("per-item seeds: predict_next of a batch of 3 equals each item alone with its seed") {
  const History batch = three_windows();
  SampleOptions batched;
  batched.steps = 3;
  batched.item_seeds = kSeeds;
  const auto together = golden_world_model().predict_next(batch, std::nullopt, batched);
  double worst_traj = 0, worst_latent = 0;
  for (std::int64_t b = 0; b < batch.latents.size(0); ++b) {
    SampleOptions single;
    single.steps = 3;
    single.seed = kSeeds[static_cast<std::size_t>(b)];
    const auto alone = golden_world_model().predict_next(item_of(batch, b), std::nullopt, single);
    worst_traj = std::max(worst_traj, rel_max(together.trajectory.slice(b, b + 1), alone.trajectory));
    worst_latent = std::max(worst_latent, rel_max(together.latent.slice(b, b + 1), alone.latent));
  }
  MESSAGE("predict_next, batch of 3 vs alone: worst trajectory rel ", worst_traj, ", worst latent rel ", worst_latent);
  CHECK(worst_traj <= kBatchTolerance);
  CHECK(worst_latent <= kBatchTolerance);
}

TEST_CASE("per-item seeds: a 2-frame rollout of a batch of 3 equals each item's rollout alone") {
  const History batch = three_windows();
  RolloutOptions batched;
  batched.frames = 2;
  batched.sample.steps = 2;
  batched.sample.item_seeds = kSeeds;
  const auto together = rollout(golden_world_model(), batch, batched);
  double worst_traj = 0, worst_latent = 0;
  for (std::int64_t b = 0; b < batch.latents.size(0); ++b) {
    RolloutOptions single;
    single.frames = 2;
    single.sample.steps = 2;
    single.sample.seed = kSeeds[static_cast<std::size_t>(b)];
    const auto alone = rollout(golden_world_model(), item_of(batch, b), single);
    for (std::int64_t f = 0; f < 2; ++f) {
      worst_traj = std::max(worst_traj, rel_max(together.trajectories[f].slice(b, b + 1), alone.trajectories[f]));
      worst_latent = std::max(worst_latent, rel_max(together.latents[f].slice(b, b + 1), alone.latents[f]));
    }
  }
  MESSAGE("rollout of 2 frames, batch of 3 vs alone: worst trajectory rel ", worst_traj, ", worst latent rel ",
          worst_latent);
  CHECK(worst_traj <= kBatchTolerance);
  CHECK(worst_latent <= kBatchTolerance);
}

TEST_CASE("per-item seeds: a seed count other than the batch is refused, naming both") {
  const History batch = three_windows();
  SampleOptions two_seeds;
  two_seeds.steps = 2;
  two_seeds.item_seeds = {1, 2};
  const std::string step_error = error_of([&] { (void)golden_world_model().predict_next(batch, std::nullopt, two_seeds); });
  MESSAGE(step_error);
  CHECK(contains(step_error, "batch of 3"));
  CHECK(contains(step_error, "2 per-item seed(s)"));
  CHECK(contains(error_of([&] { (void)golden_world_model().plan(batch, two_seeds); }), "2 per-item seed(s)"));

  RolloutOptions ro;
  ro.frames = 2;
  ro.sample = two_seeds;
  CHECK(contains(error_of([&] { (void)rollout(golden_world_model(), batch, ro); }), "batch of 3"));

  auto direct = NoiseSource::seeded_per_item({5, 6});
  CHECK(contains(error_of([&] { (void)direct.latent({4, 2, 2}); }), "batch of 4 but 2 per-item seed(s)"));
  CHECK(contains(error_of([] { (void)NoiseSource::seeded_per_item({}); }), "at least one seed"));
  SampleOptions both;
  both.item_seeds = {1};
  both.noise = NoiseSource::seeded(1);
  CHECK(contains(error_of([&] { (void)golden_world_model().plan(item_of(batch, 0), both); }), "give one"));
  SampleOptions hyp;
  hyp.item_seeds = {1};
  CHECK(contains(error_of([&] { (void)golden_world_model().plan_hypotheses(item_of(batch, 0), 2, hyp); }), "per-item seeds"));
}
