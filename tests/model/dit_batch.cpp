// Batch invariance of the DiTs (model/flux_dit.hpp): a batch runs in one pass through the blocks
// (the items folded into the rows of every product, the attention batched over them), and item i
// of that pass is item i run alone — the velocity of forward() and a sample with each solver, for
// a VisDiT-like DiT (an action vector, streams paired at batch 1) and a TrajDiT-like one (no
// action, the pipelined condition front). Items differ in condition, action, ids and noise.
// Bound: float32 within 1e-6 relative (the CPU's products sum each row the same way whatever the
// row count, so it is expected to be exact; the worst difference is printed).
#include <doctest/doctest.h>

#include <string>

#include "../metrics.hpp"
#include "dit_cases.hpp"

using namespace epona;
using namespace epona::test::dit;
using epona::test::rel_max;

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
