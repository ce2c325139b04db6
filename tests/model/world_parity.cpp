// Parity of the CPU world model with the official Epona code: every world-model case of the
// golden set (emb.*, temb.*, tok.*, mst.*, ids.*, sched.*, traj.*, vis.*, rollout.*), each
// stage fed with the stored golden inputs, sizes from configs.json. Tolerances per the golden
// README: rel <= 1e-4 (float32), 1e-3 (rollout.*), 1e-6 (ids, schedules, token indices). The
// rollout also with the VisDiT split over two shards (tensor parallelism), to the same values.
#include <doctest/doctest.h>

#include <optional>
#include <string>
#include <vector>

#include "../cpu_context.hpp"
#include "epona/core/arena.hpp"
#include "epona/cpu/thread_shard_sum.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/model/flux_dit.hpp"
#include "epona/model/mst.hpp"
#include "epona/model/pose_tokenizer.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "epona/nn/embeddings.hpp"
#include "world_golden.hpp"

using namespace epona;
using epona::test::cpu_context;
using epona::test::expect_golden;
using epona::test::first_entries;
using epona::test::Stack;
using epona::test::world_golden;

namespace {

template <class Model>
void bind_checked(Model& m, const std::string& prefix) {
  const auto& g = world_golden();
  io::BindReport report(g.weights);
  m.bind(g.weights, prefix, report);
  report.finish(true, [&](const std::string& k) { return k.rfind(prefix, 0) != 0; });
}

const model::SpatialTemporalTransformer<Cpu, float>& mst() {
  static const auto m = [] {
    model::SpatialTemporalTransformer<Cpu, float> s(model::MstConfig::from(world_golden().world()));
    bind_checked(s, "module.model.");
    return s;
  }();
  return m;
}

const model::FluxDiT<Cpu, float>& dit(bool vis) {
  static const auto make = [](bool v) {
    const auto& w = world_golden().world();
    model::FluxDiT<Cpu, float> d(v ? model::FluxDitConfig::vis(w) : model::FluxDitConfig::traj(w));
    bind_checked(d, v ? "module.dit." : "module.traj_dit.");
    return d;
  };
  static const auto traj = make(false), visual = make(true);
  return vis ? visual : traj;
}

std::int64_t batch() { return world_golden().tensor("mst.latents").size(0); }

model::DitIds golden_ids() {
  const auto& w = world_golden().world();
  return model::prepare_ids(batch(), w.latent_h(), w.latent_w(), w.tokens_per_frame(), w.traj_len);
}

}  // namespace

TEST_CASE("embeddings: Fourier (emb.*) and timestep (temb.*)") {
  const auto& g = world_golden();
  const auto coords = g.tensor("emb.fourier.coords");
  Shape fourier_shape = coords.shape();
  fourier_shape.push_back(constants::fourier_embed_dim);
  Tensor<float, Cpu> fourier(fourier_shape);
  nn::fourier_embed(coords.data(), coords.numel(), constants::fourier_embed_dim,
                    static_cast<float>(constants::fourier_max_period), fourier.data());
  expect_golden("emb.fourier.out", fourier);

  const auto t = g.tensor("temb.t");
  Tensor<float, Cpu> temb({t.numel(), constants::timestep_embed_dim});
  nn::timestep_embedding(t.data(), t.numel(), constants::timestep_embed_dim, constants::timestep_max_period,
                         static_cast<float>(constants::timestep_time_factor), temb.data());
  expect_golden("temb.out", temb);
}

TEST_CASE("pose tokenizer (tok.*, mst.pose_idx, mst.yaw_idx)") {
  const auto& g = world_golden();
  const auto tok = model::PoseTokenizer::from(g.world());
  expect_golden("tok.pose_idx", tok.poses_to_indices(g.tensor("tok.rel_pose")));
  expect_golden("tok.yaw_idx", tok.yaws_to_indices(g.tensor("tok.rel_yaw")));
  expect_golden("mst.pose_idx", tok.poses_to_indices(g.tensor("mst.rel_pose")));
  expect_golden("mst.yaw_idx", tok.yaws_to_indices(g.tensor("mst.rel_yaw")));
}

TEST_CASE("DiT position ids (ids.*)") {
  const auto ids = golden_ids();
  expect_golden("ids.img", ids.img);
  expect_golden("ids.cond", ids.cond);
  expect_golden("ids.traj", ids.traj);
}

TEST_CASE("sampling schedules (sched.*), bit-exact") {
  const auto& w = world_golden().world();
  const WorldModelConfig real;  // the shipped configuration
  const auto check = [](const std::string& name, const std::vector<float>& ours) {
    const auto golden = world_golden().tensor(name);
    REQUIRE(golden.numel() == static_cast<std::int64_t>(ours.size()));
    Tensor<float, Cpu> t({golden.numel()});
    std::copy(ours.begin(), ours.end(), t.data());
    expect_golden(name, t);
    int differing_bits = 0;
    for (std::size_t i = 0; i < ours.size(); ++i) differing_bits += ours[i] != golden.data()[i];
    CHECK_MESSAGE(differing_bits == 0, name, ": ", differing_bits, " values differ from the official fp32 grid");
  };
  check("sched.traj", flow::get_schedule(w.num_sampling_steps, w.traj_len));
  check("sched.img", flow::get_schedule(w.num_sampling_steps, w.img_tokens()));
  check("sched.real_traj_100", flow::get_schedule(100, real.traj_len));
  check("sched.real_img_100", flow::get_schedule(100, real.img_tokens()));
}

TEST_CASE("MST evaluate (mst.*), every block's output") {
  const auto& g = world_golden();
  const auto& m = mst();
  const auto& c = m.config();
  const auto latents = g.tensor("mst.latents");
  const std::int64_t B = latents.size(0);
  Tensor<float, Cpu> stt({B, c.tokens_per_frame(), c.n_embd}), pose_emb({B, 3 * c.n_embd});
  Arena<Cpu> arena(m.evaluate_workspace_bytes());
  int observed_blocks = 0;
  m.evaluate(cpu_context(), arena, latents, g.tensor("mst.pose_idx"), g.tensor("mst.yaw_idx"), stt, pose_emb,
             [&](std::int64_t b, const std::string& stage, const Tensor<float, Cpu>& x) {
               const std::string name = "mst." + stage;
               if (!g.has(name)) return;
               auto golden = g.tensor(name)[b];  // (F, T, C) of batch item b
               const double rel = test::rel_max(x, golden);
               MESSAGE(name, "[", b, "]: rel ", rel, " (limit 1e-4)");
               CHECK(rel <= 1e-4);
               observed_blocks += stage.rfind("block", 0) == 0;
             });
  CHECK(arena.high_water() == m.evaluate_workspace_bytes());
  expect_golden("mst.stt_features", stt);
  expect_golden("mst.pose_emb", pose_emb);
  // Without an observer the last block computes the last frame only (compute-budget.md §5.4).
  arena.reset();
  m.evaluate(cpu_context(), arena, latents, g.tensor("mst.pose_idx"), g.tensor("mst.yaw_idx"), stt, pose_emb);
  expect_golden("mst.stt_features", stt, " (pruned last block)");
  expect_golden("mst.pose_emb", pose_emb, " (pruned last block)");
  // Every mst.block{i}_out present in the set was checked.
  int golden_blocks = 0;
  while (g.has("mst.block" + std::to_string(golden_blocks) + "_out")) ++golden_blocks;
  CHECK(observed_blocks == golden_blocks * B);
  CHECK(g.has("mst.tokens_in"));
}

TEST_CASE("TrajDiT and VisDiT: one velocity and a full sample (traj.*, vis.*)") {
  const auto& g = world_golden();
  const auto& w = g.world();
  const auto ids = golden_ids();
  const auto cond = g.tensor("mst.stt_features"), y = g.tensor("mst.pose_emb");
  for (const bool vis : {false, true}) {
    const std::string name = vis ? "vis" : "traj";
    const auto& d = dit(vis);
    const auto& target_ids = vis ? ids.img : ids.traj;
    const auto x = g.tensor(name + ".x");
    const nn::JointRows rows{cond.size(1), x.size(1)};
    const std::int64_t steps = w.num_sampling_steps;
    Arena<Cpu> arena(std::max(d.forward_bytes(x.size(0), rows),
                              d.conditioning_bytes(x.size(0), rows) + d.sample_bytes(x.size(0), rows, steps)));
    Tensor<float, Cpu> v(x.shape());
    d.forward(cpu_context(), arena, x, target_ids, cond, ids.cond, g.tensor(name + ".t"), y, v);
    expect_golden(name + ".velocity", v);

    const auto grid = flow::get_schedule(steps, vis ? w.img_tokens() : w.traj_len);
    auto state = g.tensor(name + ".sample.noise");
    {
      ArenaScope<Cpu> scope(arena);
      const auto c = d.prepare(cpu_context(), arena, cond, ids.cond, target_ids, y);
      d.sample(cpu_context(), arena, c, grid, state);
    }
    CHECK(arena.high_water() <= arena.capacity());
    expect_golden(name + ".sample.out", state);
    if (!vis) {
      model::TrajectoryScale::from(w).denormalize(state);
      expect_golden("traj.sample.out_denorm", state);
    }
  }
}

namespace {

// The golden rollout (rollout.*) of `wm`: every step's intermediate values and results, stacked.
struct GoldenRollout {
  Stack stt, pose_idx, yaw_idx, pose_emb, traj, latents, rel_pose, rel_yaw;
  RolloutResult result;
};
GoldenRollout golden_rollout(WorldModel<Cpu, float>& wm) {
  const auto& g = world_golden();
  const auto& w = g.world();
  const std::int64_t F = w.condition_frames;
  const History start{g.tensor("mst.latents"), first_entries(g.tensor("mst.rel_pose"), F),
                      first_entries(g.tensor("mst.rel_yaw"), F)};
  const auto noise_traj = g.tensor("rollout.noise_traj"), noise_img = g.tensor("rollout.noise_img");
  const std::int64_t S = noise_traj.size(0), B = noise_traj.size(1);
  RolloutOptions opt;
  opt.frames = S;
  opt.sample.noise = NoiseSource::supplied(noise_traj, noise_img);
  const std::int64_t C = w.n_embd;
  GoldenRollout r{Stack(S, {B, w.tokens_per_frame(), C}), Stack(S, {B, 1, 2}), Stack(S, {B, 1, 1}),
                  Stack(S, {B, w.pose_emb_dim()}), Stack(S, {B, w.traj_len, 3}),
                  Stack(S, {B, w.latent_h(), w.latent_w(), w.token_dim()}), Stack(S, {B, F + 1, 2}),
                  Stack(S, {B, F + 1, 1}), {}};
  r.result = rollout(wm, start, opt, [&](const RolloutFrame<Cpu>& f) {
    r.stt.put(f.index, f.details.stt_features);
    r.pose_idx.put(f.index, f.details.pred_pose_idx);
    r.yaw_idx.put(f.index, f.details.pred_yaw_idx);
    r.pose_emb.put(f.index, f.details.pose_emb);
    r.traj.put(f.index, f.result.trajectory);
    r.latents.put(f.index, f.result.latent);
    r.rel_pose.put(f.index, f.rel_pose_window);
    r.rel_yaw.put(f.index, f.rel_yaw_window);
  });
  return r;
}
void expect_golden_rollout(const GoldenRollout& r) {
  expect_golden("rollout.stt_features", r.stt.t);
  expect_golden("rollout.pred_pose_idx", r.pose_idx.t);
  expect_golden("rollout.pred_yaw_idx", r.yaw_idx.t);
  expect_golden("rollout.pose_emb", r.pose_emb.t);
  expect_golden("rollout.predict_traj", r.traj.t);
  expect_golden("rollout.predict_latents", r.latents.t);
  expect_golden("rollout.rel_pose_after", r.rel_pose.t);
  expect_golden("rollout.rel_yaw_after", r.rel_yaw.t);
  // The returned stacks hold the same per-step results.
  CHECK(test::rel_max(r.result.trajectories, r.traj.t.reshape(r.result.trajectories.shape())) == 0);
  CHECK(test::rel_max(r.result.latents, r.latents.t.reshape(r.result.latents.shape())) == 0);
}

}  // namespace

TEST_CASE("autoregressive rollout with self-predicted actions (rollout.*)") {
  auto wm = WorldModel<Cpu, float>::load(world_golden().weights, world_golden().world());
  expect_golden_rollout(golden_rollout(wm));
}

// Tensor parallelism (docs/parallel.md): the VisDiT's heads split over two shards, each a thread
// with its own model (cpu::ThreadShardGroup); the official rollout's values within the same
// tolerances, and both shards the same bits.
TEST_CASE("the rollout with the VisDiT split over 2 shards (rollout.*)") {
  const auto& g = world_golden();
  const std::int64_t shards = 2;
  REQUIRE(g.world().n_head_dit % shards == 0);
  cpu::ThreadShardGroup group(shards);
  std::vector<std::optional<GoldenRollout>> parts(shards);
  group.run([&](std::int64_t r) {
    const auto sum = group.shard(r);
    auto wm = WorldModel<Cpu, float>::load(g.weights, g.world(), {{r, shards}, &sum});
    wm.context().set_threads(1);
    parts[r] = golden_rollout(wm);
  });
  expect_golden_rollout(*parts[0]);
  CHECK(test::rel_max(parts[1]->result.latents, parts[0]->result.latents) == 0);
  CHECK(test::rel_max(parts[1]->result.trajectories, parts[0]->result.trajectories) == 0);
  using World = WorldModel<Cpu, float>;
  const auto without_sum = [&] { return World::load(g.weights, g.world(), {{0, 2}, nullptr}); };
  CHECK_THROWS_WITH_AS(without_sum(), doctest::Contains("needs its group's sum"), Error);
}
