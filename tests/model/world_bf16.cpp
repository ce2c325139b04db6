// The world model with bfloat16 weights (float32 activations) against the float32 golden
// outputs, per stage, held to the golden README's bf16 rule: at most twice the error of the
// official bf16 inference recipe (manifest.json `tolerance_official_bf16_recipe`). The rollout
// is excluded (it diverges in bf16, as the README says).
#include <doctest/doctest.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "epona/core/arena.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/model/world_model.hpp"
#include "world_golden.hpp"

using namespace epona;
using epona::test::world_golden;

namespace {

double official_bf16_error(const std::string& name) {
  static const nlohmann::json manifest = [] {
    std::ifstream in(test::golden_dir() + "/manifest.json");
    return nlohmann::json::parse(in);
  }();
  return manifest.at("tolerance_official_bf16_recipe").at("official_recipe_vs_fp32_golden").at(name).at("rel_max").get<double>();
}

void expect_bf16(const std::string& name, const Tensor<float, Cpu>& ours) {
  const auto golden = world_golden().tensor(name);
  REQUIRE(ours.shape() == golden.shape());
  const double rel = test::rel_max(ours, golden), limit = 2 * official_bf16_error(name);
  MESSAGE(name, " (bf16 weights): rel ", rel, " (official bf16 recipe ", limit / 2, ", limit ", limit, ")");
  CHECK(rel <= limit);
}

}  // namespace

TEST_CASE("bf16 weights: MST, one DiT velocity each, and both samplers") {
  const auto& g = world_golden();
  const auto& w = g.world();
  auto wm = WorldModel<Cpu, bf16>::load(g.weights, w);
  auto& ctx = wm.context();
  const auto latents = g.tensor("mst.latents");
  const std::int64_t B = latents.size(0);
  Tensor<float, Cpu> stt({B, w.tokens_per_frame(), w.n_embd}), pose_emb({B, w.pose_emb_dim()});
  {
    Arena<Cpu> arena(wm.mst().evaluate_workspace_bytes(B));
    wm.mst().evaluate(ctx, arena, latents, g.tensor("mst.pose_idx"), g.tensor("mst.yaw_idx"), stt, pose_emb);
  }
  expect_bf16("mst.stt_features", stt);
  expect_bf16("mst.pose_emb", pose_emb);

  const auto ids = model::prepare_ids(B, w.latent_h(), w.latent_w(), w.tokens_per_frame(), w.traj_len);
  const auto cond = g.tensor("mst.stt_features"), y = g.tensor("mst.pose_emb");
  for (const bool vis : {false, true}) {
    const std::string name = vis ? "vis" : "traj";
    const auto& dit = vis ? wm.vis_dit() : wm.traj_dit();
    const auto& target_ids = vis ? ids.img : ids.traj;
    const auto x = g.tensor(name + ".x");
    const nn::JointRows rows{cond.size(1), x.size(1)};
    Arena<Cpu> arena(dit.forward_bytes(B, rows) + dit.sample_bytes(B, rows, w.num_sampling_steps));
    Tensor<float, Cpu> v(x.shape());
    dit.forward(ctx, arena, x, target_ids, cond, ids.cond, g.tensor(name + ".t"), y, v);
    expect_bf16(name + ".velocity", v);
    auto state = g.tensor(name + ".sample.noise");
    const auto c = dit.prepare(ctx, arena, cond, ids.cond, target_ids, y);
    dit.sample(ctx, arena, c, flow::get_schedule(w.num_sampling_steps, vis ? w.img_tokens() : w.traj_len), state);
    expect_bf16(name + ".sample.out", state);
  }
}
