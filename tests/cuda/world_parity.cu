// The world model on the GPU against the golden set (EPONA_GOLDEN_DIR, default the copy in
// tests/data/golden): in float32, every world-model case (mst.* with every block, traj.*,
// vis.*, rollout.*) with the CPU test's tolerances (golden README: rel_max <= 1e-4, 1e-3 for
// rollout.*); in bf16 (bf16 weights and activations, float32 MST residual stream), every
// stage within twice the error of the official bf16 recipe (manifest.json), and the rollout's
// first step likewise, in the manifest's units (later steps diverge in bf16, README: reported,
// checked finite). The whole arena and every output are poisoned (0xFF: NaN) before each GPU
// call, so a value the model reads or returns without writing it fails. Then the world model with
// its VisDiT split in two (WorldModel::VisShard; the shards sharing the GPU, cuda::StreamShardGroup):
// predict_next as the whole model's (check_shard_results), the trajectory (the whole TrajDiT on
// every shard) bit for bit.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "../model/world_golden.hpp"
#include "cuda_test_util.cuh"
#include "epona/cuda/backend.cuh"
#include "epona/cuda/runtime/stream_shard_sum.cuh"
#include "epona/flow/schedule.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"

using namespace epona;
using epona::test::first_entries;
using epona::test::Stack;
using epona::test::world_golden;

namespace {

template <class W>
WorldModel<Cuda, W>& gpu_model() {
  static auto wm = WorldModel<Cuda, W>::load(world_golden().weights, world_golden().world());
  return wm;
}

// Every byte of the arena set to 0xFF (NaN in float32 and bf16), then released.
void poison_arena(cuda::Context& ctx, Arena<Cuda>& arena) {
  arena.reset();
  auto all = arena.take<unsigned char>({static_cast<std::int64_t>(arena.capacity())});
  cuda::fill_bytes(ctx, all, 0xFF);
  arena.reset();
}

template <class T>
Tensor<T, Cuda> poisoned(cuda::Context& ctx, const Shape& shape) {
  Tensor<T, Cuda> t(shape);
  cuda::fill_bytes(ctx, t, 0xFF);
  return t;
}

template <class T>
Tensor<float, Cpu> host(cuda::Context& ctx, const Tensor<T, Cuda>& t) {
  return test::download(ctx, t);
}

double official_bf16_error(const std::string& name) {
  static const nlohmann::json manifest = [] {
    std::ifstream in(test::golden_dir() + "/manifest.json");
    return nlohmann::json::parse(in);
  }();
  return manifest.at("tolerance_official_bf16_recipe").at("official_recipe_vs_fp32_golden").at(name).at("rel_max").get<double>();
}

// bf16 bound: twice the official bf16 recipe's error of `recipe_name` (the tensor `name`
// itself unless a slice of a rollout tensor is compared).
void expect_bf16(const std::string& name, const Tensor<float, Cpu>& ours, const Tensor<float, Cpu>& golden,
                 const std::string& recipe_name) {
  REQUIRE(ours.shape() == golden.shape());
  const double rel = test::rel_max(ours, golden), limit = 2 * official_bf16_error(recipe_name);
  MESSAGE(name, " (GPU bf16): rel ", rel, " (official bf16 recipe ", limit / 2, ", limit ", limit, ")");
  CHECK(rel <= limit);
}
void expect_bf16(const std::string& name, const Tensor<float, Cpu>& ours) {
  expect_bf16(name, ours, world_golden().tensor(name), name);
}

// max |a − b| (b empty: max |a|).
double max_abs(const Tensor<float, Cpu>& a, const Tensor<float, Cpu>* b = nullptr) {
  double m = 0;
  for (std::int64_t i = 0; i < a.numel(); ++i)
    m = std::max(m, std::abs(double(a.data()[i]) - (b ? double(b->data()[i]) : 0.0)));
  return m;
}

// The first rollout step against twice the official recipe's error, in the manifest's units. The
// manifest measures a rollout tensor over every step: max |recipe − golden| over all steps, over
// max |golden| over all steps. Step 0 alone is therefore scaled by the same max |golden| of all
// steps. (Scaled by step 0's own max, a step whose golden values are small — the first
// waypoint's yaw, a window of slow motions — turns the same error into a larger figure: on 12
// conformance sets of other sizes the official recipe's own step 0 measured that way reached
// 4.1x its manifest figure; docs/world-model.md, "bf16 margins of the rollout".)
void expect_bf16_first_step(const std::string& name, const Tensor<float, Cpu>& ours, const Tensor<float, Cpu>& golden) {
  REQUIRE(ours[0].shape() == golden[0].shape());
  const auto ours0 = ours[0], golden0 = golden[0];
  const double scale = max_abs(golden), err = max_abs(ours0, &golden0);
  const double rel = scale > 0 ? err / scale : err, recipe = official_bf16_error(name), limit = 2 * recipe;
  MESSAGE(name, "[step 0] (GPU bf16): rel ", rel, " (official bf16 recipe ", recipe, ", limit ", limit,
          ", margin ", rel > 0 ? limit / rel : INFINITY, "x; over step 0's own max |golden|: ",
          test::rel_max(ours[0], golden[0]), ")");
  CHECK(rel <= limit);
}

std::int64_t batch() { return world_golden().tensor("mst.latents").size(0); }

model::DitIds golden_ids() {
  const auto& w = world_golden().world();
  return model::prepare_ids(batch(), w.latent_h(), w.latent_w(), w.tokens_per_frame(), w.traj_len);
}

// MST evaluate on the GPU; `observe` sees every block when given (then the last block is full).
template <class W>
std::pair<Tensor<float, Cpu>, Tensor<float, Cpu>> run_mst(const model::MstObserver<Cuda>& observe = {}) {
  const auto& g = world_golden();
  auto& wm = gpu_model<W>();
  auto& ctx = wm.context();
  const auto& c = wm.mst().config();
  const auto latents = cuda::to_device(ctx, g.tensor("mst.latents"));
  const std::int64_t B = latents.size(0);
  auto stt = poisoned<float>(ctx, {B, c.tokens_per_frame(), c.n_embd});
  auto emb = poisoned<float>(ctx, {B, 3 * c.n_embd});
  Arena<Cuda> arena(wm.mst().evaluate_workspace_bytes(B));
  poison_arena(ctx, arena);
  wm.mst().evaluate(ctx, arena, latents, g.tensor("mst.pose_idx"), g.tensor("mst.yaw_idx"), stt, emb, observe);
  CHECK(arena.high_water() <= wm.mst().evaluate_workspace_bytes(B));
  return {host(ctx, stt), host(ctx, emb)};
}

// One velocity (forward) and one sample of a DiT on the GPU, from the golden inputs.
template <class W>
std::pair<Tensor<float, Cpu>, Tensor<float, Cpu>> run_dit(bool vis) {
  const auto& g = world_golden();
  const auto& w = g.world();
  auto& wm = gpu_model<W>();
  auto& ctx = wm.context();
  const auto& d = vis ? wm.vis_dit() : wm.traj_dit();
  const std::string name = vis ? "vis" : "traj";
  const auto ids = golden_ids();
  const auto& target_ids = vis ? ids.img : ids.traj;
  const auto cond = cuda::to_device(ctx, g.tensor("mst.stt_features"));
  const auto y = cuda::to_device(ctx, g.tensor("mst.pose_emb"));
  const auto x = cuda::to_device(ctx, g.tensor(name + ".x"));
  const nn::JointRows rows{cond.size(1), x.size(1)};
  const std::int64_t B = x.size(0), steps = w.num_sampling_steps;
  Arena<Cuda> arena(std::max(d.forward_bytes(B, rows), d.conditioning_bytes(B, rows) + d.sample_bytes(B, rows, steps)));

  poison_arena(ctx, arena);
  auto v = poisoned<W>(ctx, x.shape());
  d.forward(ctx, arena, x, target_ids, cond, ids.cond, g.tensor(name + ".t"), y, v);
  const auto velocity = host(ctx, v);
  {
    // forward_bytes is exactly what forward takes (a poisoned arena's high water is its capacity).
    Arena<Cuda> exact(d.forward_bytes(B, rows));
    auto v2 = poisoned<W>(ctx, x.shape());
    d.forward(ctx, exact, x, target_ids, cond, ids.cond, g.tensor(name + ".t"), y, v2);
    CHECK(exact.high_water() == d.forward_bytes(B, rows));
    CHECK(test::rel_max(host(ctx, v2), velocity) == 0);
  }

  poison_arena(ctx, arena);
  auto state = cuda::to_device(ctx, g.tensor(name + ".sample.noise"));
  {
    ArenaScope<Cuda> scope(arena);
    const auto c = d.prepare(ctx, arena, cond, ids.cond, target_ids, y);
    d.sample(ctx, arena, c, flow::get_schedule(steps, vis ? w.img_tokens() : w.traj_len), state);
  }
  CHECK(arena.high_water() <= arena.capacity());
  return {velocity, host(ctx, state)};
}

const char* const kRolloutTensors[] = {"rollout.stt_features", "rollout.pred_pose_idx", "rollout.pred_yaw_idx",
                                       "rollout.pose_emb",     "rollout.predict_traj",  "rollout.predict_latents",
                                       "rollout.rel_pose_after", "rollout.rel_yaw_after"};

// The golden rollout case on the GPU; returns the stacked per-step outputs by name.
template <class W>
std::map<std::string, Tensor<float, Cpu>> run_rollout() {
  const auto& g = world_golden();
  const auto& w = g.world();
  auto& wm = gpu_model<W>();
  auto& ctx = wm.context();
  const std::int64_t F = w.condition_frames;
  const History start{g.tensor("mst.latents"), first_entries(g.tensor("mst.rel_pose"), F),
                      first_entries(g.tensor("mst.rel_yaw"), F)};
  const auto noise_traj = g.tensor("rollout.noise_traj"), noise_img = g.tensor("rollout.noise_img");
  const std::int64_t S = noise_traj.size(0), B = noise_traj.size(1), C = w.n_embd;
  RolloutOptions opt;
  opt.frames = S;
  opt.sample.noise = NoiseSource::supplied(noise_traj, noise_img);
  std::map<std::string, Stack> st;
  st.emplace("rollout.stt_features", Stack(S, {B, w.tokens_per_frame(), C}));
  st.emplace("rollout.pred_pose_idx", Stack(S, {B, 1, 2}));
  st.emplace("rollout.pred_yaw_idx", Stack(S, {B, 1, 1}));
  st.emplace("rollout.pose_emb", Stack(S, {B, w.pose_emb_dim()}));
  st.emplace("rollout.predict_traj", Stack(S, {B, w.traj_len, 3}));
  st.emplace("rollout.predict_latents", Stack(S, {B, w.latent_h(), w.latent_w(), w.token_dim()}));
  st.emplace("rollout.rel_pose_after", Stack(S, {B, F + 1, 2}));
  st.emplace("rollout.rel_yaw_after", Stack(S, {B, F + 1, 1}));
  rollout(wm, start, opt, [&](const RolloutFrame<Cuda>& f) {
    st.at("rollout.stt_features").put(f.index, host(ctx, f.details.stt_features));
    st.at("rollout.pred_pose_idx").put(f.index, f.details.pred_pose_idx);
    st.at("rollout.pred_yaw_idx").put(f.index, f.details.pred_yaw_idx);
    st.at("rollout.pose_emb").put(f.index, host(ctx, f.details.pose_emb));
    st.at("rollout.predict_traj").put(f.index, f.result.trajectory);
    st.at("rollout.predict_latents").put(f.index, f.result.latent);
    st.at("rollout.rel_pose_after").put(f.index, f.rel_pose_window);
    st.at("rollout.rel_yaw_after").put(f.index, f.rel_yaw_window);
  });
  std::map<std::string, Tensor<float, Cpu>> out;
  for (auto& [k, v] : st) out.emplace(k, v.t);
  return out;
}

bool all_finite(const Tensor<float, Cpu>& t) {
  for (std::int64_t i = 0; i < t.numel(); ++i)
    if (!std::isfinite(t.data()[i])) return false;
  return true;
}

}  // namespace

TEST_CASE("GPU float32: MST evaluate (mst.*), every block's output, pruned and full") {
  EPONA_REQUIRE_GPU();
  const auto& g = world_golden();
  auto& ctx = gpu_model<float>().context();
  int observed_blocks = 0;
  const auto [stt_full, emb_full] = run_mst<float>([&](std::int64_t b, const std::string& stage, const Tensor<float, Cuda>& x) {
    const std::string name = "mst." + stage;
    if (!g.has(name)) return;
    const double rel = test::rel_max(host(ctx, x), g.tensor(name)[b]);
    MESSAGE(name, "[", b, "] (GPU f32): rel ", rel, " (limit 1e-4)");
    CHECK(rel <= 1e-4);
    observed_blocks += stage.rfind("block", 0) == 0;
  });
  test::expect_golden("mst.stt_features", stt_full, " (GPU f32, observed)");
  test::expect_golden("mst.pose_emb", emb_full, " (GPU f32, observed)");
  int golden_blocks = 0;
  while (g.has("mst.block" + std::to_string(golden_blocks) + "_out")) ++golden_blocks;
  CHECK(observed_blocks == golden_blocks * batch());
  const auto [stt, emb] = run_mst<float>();
  test::expect_golden("mst.stt_features", stt, " (GPU f32, pruned last block)");
  test::expect_golden("mst.pose_emb", emb, " (GPU f32, pruned last block)");
}

TEST_CASE("GPU float32: TrajDiT and VisDiT, one velocity and a full sample (traj.*, vis.*)") {
  EPONA_REQUIRE_GPU();
  for (const bool vis : {false, true}) {
    const std::string name = vis ? "vis" : "traj";
    const auto [v, sample] = run_dit<float>(vis);
    test::expect_golden(name + ".velocity", v, " (GPU f32)");
    test::expect_golden(name + ".sample.out", sample, " (GPU f32)");
    if (!vis) {
      auto denorm = sample.clone();
      model::TrajectoryScale::from(world_golden().world()).denormalize(denorm);
      test::expect_golden("traj.sample.out_denorm", denorm, " (GPU f32)");
    }
  }
  // The sampling loop was recorded once per DiT and replayed (twice would mean a key mismatch).
  if (gpu_model<float>().context().policy().graphs) {
    CHECK(gpu_model<float>().traj_dit().sampler_graph().captures() == 1);
    CHECK(gpu_model<float>().vis_dit().sampler_graph().captures() == 1);
  }
}

TEST_CASE("GPU float32: autoregressive rollout with self-predicted actions (rollout.*)") {
  EPONA_REQUIRE_GPU();
  const auto out = run_rollout<float>();
  for (const char* name : kRolloutTensors) test::expect_golden(name, out.at(name), " (GPU f32)");
  // A second rollout replays the recorded sampler graphs (same arena layout) and is identical.
  const int traj_captures = gpu_model<float>().traj_dit().sampler_graph().captures();
  const auto again = run_rollout<float>();
  for (const char* name : kRolloutTensors) CHECK_MESSAGE(test::rel_max(again.at(name), out.at(name)) == 0, std::string(name));
  CHECK(gpu_model<float>().traj_dit().sampler_graph().captures() == traj_captures);
}

TEST_CASE("GPU bf16: MST, one DiT velocity each, both samplers, within twice the official bf16 recipe") {
  EPONA_REQUIRE_GPU();
  const auto [stt, emb] = run_mst<bf16>();
  expect_bf16("mst.stt_features", stt);
  expect_bf16("mst.pose_emb", emb);
  for (const bool vis : {false, true}) {
    const std::string name = vis ? "vis" : "traj";
    const auto [v, sample] = run_dit<bf16>(vis);
    expect_bf16(name + ".velocity", v);
    expect_bf16(name + ".sample.out", sample);
  }
}

TEST_CASE("GPU bf16: rollout — first step within twice the official bf16 recipe, all steps finite") {
  EPONA_REQUIRE_GPU();
  const auto out = run_rollout<bf16>();
  const auto reference = run_rollout<float>();  // the float32 run of this port, for the report
  for (const char* name : kRolloutTensors) {
    const auto& ours = out.at(name);
    CHECK_MESSAGE(all_finite(ours), std::string(name), " has non-finite values");
    const auto golden = world_golden().tensor(name);
    expect_bf16_first_step(name, ours, golden);
    MESSAGE(std::string(name), " (GPU bf16, all steps): rel vs golden ", test::rel_max(ours, golden), ", vs the GPU float32 run ",
            test::rel_max(ours, reference.at(name)), " (official bf16 recipe ", official_bf16_error(name), ")");
  }
}

TEST_CASE_TEMPLATE("a world model with its VisDiT split over 2 shards sharing the GPU predicts the whole model's frame",
                   W, float, bf16) {
  EPONA_REQUIRE_GPU();
  const auto& g = world_golden();
  const std::int64_t F = g.world().condition_frames, shards = 2;
  REQUIRE(g.world().n_head_dit % shards == 0);
  const History h{g.tensor("mst.latents").slice(0, 1).clone(), first_entries(g.tensor("mst.rel_pose"), F).slice(0, 1).clone(),
                  first_entries(g.tensor("mst.rel_yaw"), F).slice(0, 1).clone()};
  SampleOptions opt;
  opt.seed = 17;
  opt.steps = 4;
  const StepResult whole = gpu_model<W>().predict_next(h, std::nullopt, opt);
  const StepResult f32 = gpu_model<float>().predict_next(h, std::nullopt, opt);
  cuda::StreamShardGroup<W> group(shards);
  std::vector<StepResult> parts(shards);
  group.run([&](std::int64_t r) {
    const auto sum = group.shard(r);
    auto m = WorldModel<Cuda, W>::load(g.weights, g.world(), {{r, shards}, &sum});
    m.context().policy().graphs = false;
    m.context().policy().gemm_tuning = cuda::GemmTuning::Off;
    m.context().policy().poison_new_buffers = true;
    parts[r] = m.predict_next(h, std::nullopt, opt);
    m.context().synchronize();
  });
  std::vector<test::HostF> latents;
  for (const auto& p : parts) {
    CHECK(test::count_bit_differences(p.trajectory, whole.trajectory) == 0);
    latents.push_back(p.latent);
  }
  test::check_shard_results<W>(latents, whole.latent, f32.latent,
                               std::string("world model, ") + test::type_name<W>() + ", VisDiT over 2 shards");
}
