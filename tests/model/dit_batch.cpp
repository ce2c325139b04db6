// Batch invariance of the DiTs (model/flux_dit.hpp): a batch runs in one pass through the blocks
// (the items folded into the rows of every product, the attention batched over them), and item i
// of that pass is item i run alone — the velocity of forward() and a sample with each solver, for
// a VisDiT-like DiT (an action vector, streams paired at batch 1) and a TrajDiT-like one (no
// action, the pipelined condition front). Items differ in condition, action, ids and noise.
// Bound: float32 within 1e-6 relative (the CPU's products sum each row the same way whatever the
// row count, so it is expected to be exact; the worst difference is printed).
#include <doctest/doctest.h>

#include <random>
#include <string>

#include "epona/core/arena.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/model/flux_dit.hpp"
#include "../metrics.hpp"

using namespace epona;
using epona::test::rel_max;

namespace {

using Dit = model::FluxDiT<Cpu, float>;

cpu::Context& ctx() {
  static cpu::Context c;
  return c;
}

Tensor<float> random(const Shape& shape, std::uint32_t seed, float scale = 1.f) {
  std::mt19937 gen(seed);
  std::normal_distribution<float> dist(0.f, scale);
  Tensor<float> t(shape);
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = dist(gen);
  return t;
}

// Item b of a batched tensor as a batch of one.
Tensor<float> item(const Tensor<float>& t, std::int64_t b) {
  Shape s = t.shape();
  s[0] = 1;
  return t.slice(b, b + 1).clone().reshape(s);
}

struct Case {
  const char* name;
  model::FluxDitConfig config;
  nn::JointRows rows;
};

Case vis_like() {
  model::FluxDitConfig c;
  c.in_channels = c.out_channels = 8;
  c.context_in_dim = 24;
  c.hidden_size = 64;
  c.num_heads = 4;
  c.depth = 2;
  c.depth_single_blocks = 2;
  c.vec_in_dim = 12;
  c.axes_dim = {4, 6, 6};
  return {"VisDiT-like (paired streams, an action)", c, {10, 9}};
}
Case traj_like() {
  Case c = vis_like();
  c.name = "TrajDiT-like (unpaired streams, pipelined front)";
  c.config.vec_in_dim = 0;
  c.config.input_name = "traj_in";
  c.config.in_channels = c.config.out_channels = 3;
  c.rows = {10, 3};
  return c;
}

// The inputs of `items` scenes: condition, action, ids (each item its own), noise.
struct Inputs {
  Tensor<float> cond, y, cond_ids, target_ids, x;
};
Inputs inputs(const Case& k, std::int64_t items) {
  const auto& c = k.config;
  Inputs in{random({items, k.rows.cond, c.context_in_dim}, 1), random({items, std::max<std::int64_t>(c.vec_in_dim, 1)}, 2),
            Tensor<float>({items, k.rows.cond, 3}), Tensor<float>({items, k.rows.target, 3}),
            random({items, k.rows.target, c.in_channels}, 3)};
  if (c.vec_in_dim == 0) in.y = Tensor<float>();
  for (std::int64_t b = 0; b < items; ++b) {
    for (std::int64_t r = 0; r < k.rows.cond; ++r) in.cond_ids.at(b, r, 0) = float(b);
    for (std::int64_t r = 0; r < k.rows.target; ++r)
      for (std::int64_t a = 0; a < 3; ++a) in.target_ids.at(b, r, a) = float(r + a * b);
  }
  return in;
}
Inputs item(const Inputs& in, std::int64_t b) {
  return {item(in.cond, b), in.y.empty() ? Tensor<float>() : item(in.y, b), item(in.cond_ids, b),
          item(in.target_ids, b), item(in.x, b)};
}

Tensor<float> velocity(const Dit& dit, const Inputs& in, const Tensor<float>& t) {
  const std::int64_t batch = in.x.size(0);
  const nn::JointRows rows{in.cond.size(1), in.x.size(1)};
  Arena<Cpu> arena(dit.forward_bytes(batch, rows));
  Tensor<float> v(in.x.shape());
  dit.forward(ctx(), arena, in.x, in.target_ids, in.cond, in.cond_ids, t, in.y, v);
  return v;
}

Tensor<float> sample(const Dit& dit, const Inputs& in, std::int64_t steps, flow::SolverKind kind) {
  const std::int64_t batch = in.x.size(0);
  const nn::JointRows rows{in.cond.size(1), in.x.size(1)};
  Arena<Cpu> arena(dit.conditioning_bytes(batch, rows) + dit.sample_bytes(batch, rows, steps, kind));
  auto state = in.x.clone();
  const auto c = dit.prepare(ctx(), arena, in.cond, in.cond_ids, in.target_ids, in.y);
  dit.sample(ctx(), arena, c, flow::get_schedule(steps, rows.target), state, kind);
  return state;
}

}  // namespace

TEST_CASE("a batch in one pass gives each item what it gives alone") {
  const std::int64_t items = 3;
  for (const Case& k : {vis_like(), traj_like()}) {
    CAPTURE(std::string(k.name));
    Dit dit(k.config);
    dit.randomize(5);
    const Inputs batch = inputs(k, items);
    Tensor<float> t({items});
    for (std::int64_t b = 0; b < items; ++b) t.data()[b] = 0.2f + 0.3f * float(b);
    const auto v = velocity(dit, batch, t);
    double worst = 0;
    for (std::int64_t b = 0; b < items; ++b) {
      Tensor<float> tb({1});
      tb.data()[0] = t.data()[b];
      worst = std::max(worst, rel_max(item(v, b), velocity(dit, item(batch, b), tb)));
    }
    MESSAGE(std::string(k.name), ": forward, batch ", items, " vs each alone: worst rel ", worst);
    CHECK(worst <= 1e-6);
    for (const auto kind : {flow::SolverKind::euler, flow::SolverKind::heun}) {
      const auto sampled = sample(dit, batch, 4, kind);
      double worst_sample = 0;
      for (std::int64_t b = 0; b < items; ++b)
        worst_sample = std::max(worst_sample, rel_max(item(sampled, b), sample(dit, item(batch, b), 4, kind)));
      MESSAGE(std::string(k.name), ": ", std::string(flow::solver_name(kind)), " x 4 steps, batch ", items, " vs each alone: worst rel ",
              worst_sample);
      CHECK(worst_sample <= 1e-6);
    }
  }
}

TEST_CASE("the items really differ (the invariance test compares distinct results)") {
  const Case k = vis_like();
  Dit dit(k.config);
  dit.randomize(5);
  const auto sampled = sample(dit, inputs(k, 2), 2, flow::SolverKind::euler);
  CHECK(rel_max(item(sampled, 0), item(sampled, 1)) > 1e-2);
}

TEST_CASE("a batch larger than one pass folds runs in several passes, each item as alone") {
  const Case k = traj_like();
  Dit dit(k.config);
  dit.randomize(5);
  const std::int64_t items = Dit::kMaxFoldedItems + 2;
  const Inputs batch = inputs(k, items);
  Tensor<float> t({items});
  for (std::int64_t b = 0; b < items; ++b) t.data()[b] = 0.5f;
  const auto v = velocity(dit, batch, t);
  const auto sampled = sample(dit, batch, 2, flow::SolverKind::euler);
  Tensor<float> tb({1});
  tb.data()[0] = 0.5f;
  double worst = 0;
  for (const std::int64_t b : {std::int64_t{0}, Dit::kMaxFoldedItems - 1, Dit::kMaxFoldedItems, items - 1}) {
    worst = std::max(worst, rel_max(item(v, b), velocity(dit, item(batch, b), tb)));
    worst = std::max(worst, rel_max(item(sampled, b), sample(dit, item(batch, b), 2, flow::SolverKind::euler)));
  }
  MESSAGE("batch of ", items, " (passes of ", Dit::kMaxFoldedItems, "): worst rel against items alone ", worst);
  CHECK(worst <= 1e-6);
}
