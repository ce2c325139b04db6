// bench_gpu_batch — issue #39's table on one GPU at the real configuration (512x1024 frames, the
// shipped widths and depths, 100 sampling steps, bf16 weights, random weights): what Bt scenes
// at once cost, and what a fan of K plan hypotheses of one scene costs.
//   plan_bB    WorldModel::plan of a window of Bt scenes (MST + TrajDiT-100)
//   step_bB    predict_next of Bt scenes (MST + TrajDiT-100 + VisDiT-100, self-predicted action)
//   decode_bB  the DC-AE decode of Bt frames (its own context)
//   hyp_kK     plan_hypotheses(K) of one scene, against plan_b1 (the MST once, the TrajDiT over K)
// Each row: median milliseconds per call over the repeats (CUDA events after a warm-up call,
// host to host), the same per scene (or per hypothesis), and the ratio to batch 1 per scene.
// One JSON object per line, then a readable table. The model runs a batch item by item today
// (docs/world-model.md), so this is the baseline that true batching is measured against.
// Usage: bench_gpu_batch [--repeats N] [--max-batch B] [--max-hypotheses K]
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "epona/core/rng.hpp"
#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"
#include "epona/model/dcae.hpp"
#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"
#include "bench_stats.hpp"
#include "gpu_event_timer.cuh"

using namespace epona;

namespace {

struct Options {
  int repeats = 3;
  std::int64_t max_batch = 16, max_hypotheses = 64;
};

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const auto value = [&]() -> long long {
      EPONA_CHECK(i + 1 < argc, a, " needs a value");
      char* end = nullptr;
      const long long v = std::strtoll(argv[++i], &end, 10);
      EPONA_CHECK(end && *end == 0 && v >= 1 && v <= 1024, a, " takes a whole number in [1, 1024], got '", argv[i], "'");
      return v;
    };
    if (a == "--repeats") o.repeats = int(value());
    else if (a == "--max-batch") o.max_batch = value();
    else if (a == "--max-hypotheses") o.max_hypotheses = value();
    else fail("unknown option '", a, "' (--repeats N, --max-batch B, --max-hypotheses K)");
  }
  return o;
}

using bench::median;

// A row: the call's median, per item, and per item against `single` (the batch-1 row's per item).
struct Row {
  std::string name;
  double ms = 0, per_item = 0, ratio = 0;
};
Row emit(const std::string& name, const std::vector<double>& runs, std::int64_t items, double single_per_item) {
  Row r{name, median(runs), median(runs) / double(items), 0};
  r.ratio = single_per_item > 0 ? r.per_item / single_per_item : 1.0;
  std::printf("{\"name\": \"%s\", \"ms\": %.3f, \"items\": %lld, \"per_item_ms\": %.3f, \"per_item_vs_one\": %.3f}\n",
              name.c_str(), r.ms, static_cast<long long>(items), r.per_item, r.ratio);
  std::fflush(stdout);
  return r;
}

// A window of Bt scenes driving forward: random latents, about 2 m per frame.
History window(const WorldModelConfig& cfg, std::int64_t Bt) {
  TorchGenerator gen(0);
  const std::int64_t F = cfg.condition_frames;
  History h{gen.randn({Bt, F, cfg.img_tokens(), cfg.token_dim()}), gen.randn({Bt, F, 2}), gen.randn({Bt, F, 1})};
  for (std::int64_t b = 0; b < Bt; ++b)
    for (std::int64_t f = 0; f < F; ++f) h.rel_pose.at(b, f, 0) = 2.0f + 0.5f * h.rel_pose.at(b, f, 0);
  return h;
}

int run(const Options& o) {
  WorldModelConfig cfg;  // the shipped configuration
  auto wm = WorldModel<Cuda, bf16>::load(model::random_world_weights(cfg, 1), cfg);
  auto& ctx = wm.context();
  std::printf("# device: %s; bf16 weights, %lld steps; repeats %d\n", ctx.info().name.c_str(),
              static_cast<long long>(cfg.num_sampling_steps), o.repeats);
  DcaeConfig dcfg;
  Dcae<Cuda, bf16> dcae(dcfg);
  dcae.randomize(1);
  cuda::Context dctx;
  SampleOptions opt;
  opt.seed = 7;
  std::vector<Row> rows;
  const auto time = [&](cuda::Context& c, const std::function<void()>& fn) {
    return bench::event_times_ms(c, o.repeats, 1, fn);  // the warm-up call records the graphs
  };
  double plan1 = 0, step1 = 0, decode1 = 0;
  for (std::int64_t Bt = 1; Bt <= o.max_batch; Bt *= 2) {
    const History h = window(cfg, Bt);
    const std::string b = "_b" + std::to_string(Bt);
    rows.push_back(emit("plan" + b, time(ctx, [&] { (void)wm.plan(h, opt); }), Bt, plan1));
    if (Bt == 1) plan1 = rows.back().per_item;
    rows.push_back(emit("step" + b, time(ctx, [&] { (void)wm.predict_next(h, std::nullopt, opt); }), Bt, step1));
    if (Bt == 1) step1 = rows.back().per_item;
    TorchGenerator gen(3);
    const auto z = BackendTraits<Cuda>::upload(gen.randn({Bt, dcfg.latent_channels, cfg.latent_h(), cfg.latent_w()}));
    rows.push_back(emit("decode" + b, time(dctx, [&] { (void)dcae.decode(dctx, z, false); }), Bt, decode1));
    if (Bt == 1) decode1 = rows.back().per_item;
  }
  const History one = window(cfg, 1);
  for (std::int64_t K = 1; K <= o.max_hypotheses; K *= 2)
    rows.push_back(emit("hyp_k" + std::to_string(K), time(ctx, [&] { (void)wm.plan_hypotheses(one, K, opt); }), 1,
                        plan1));
  std::printf("\n%-12s %12s %14s %16s\n", "row", "ms / call", "ms / item", "item vs batch 1");
  for (const Row& r : rows) std::printf("%-12s %12.2f %14.2f %16.3f\n", r.name.c_str(), r.ms, r.per_item, r.ratio);
  std::printf("(hyp_kK: one scene, so 'item' is the call and the ratio is the call against one plan)\n");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    if (!cuda::has_gpu()) {
      std::printf("no CUDA device: nothing to measure\n");
      return 0;
    }
    return run(parse(argc, argv));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_gpu_batch: %s\n", e.what());
    return 1;
  }
}
