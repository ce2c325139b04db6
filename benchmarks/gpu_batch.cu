// bench_gpu_batch — issue #39's table on one GPU at the real configuration (512x1024 frames, the
// shipped widths and depths, 100 sampling steps, bf16 weights, random weights): what Bt scenes
// at once cost, and what a fan of K plan hypotheses of one scene costs.
//   mst_bB      the MST over Bt windows (folded in passes of up to 8), and mst1_bB the same
//               with one window per pass (as before the fold), alternating in the same run
//   plan_bB     WorldModel::plan of a window of Bt scenes (MST + TrajDiT-100)
//   step_bB     predict_next of Bt scenes (MST + TrajDiT-100 + VisDiT-100, self-predicted action)
//   decode_bB   the DC-AE decode of Bt frames (its own context)
//   traj100_bB  the TrajDiT's 100-step sample of Bt items alone (conditioning prepared outside)
//   vis100_bB   the VisDiT's 100-step sample of Bt items alone
//   hyp_kK      plan_hypotheses(K) of one scene, against plan_b1 (the MST once, the TrajDiT over K)
// Each row: median milliseconds per call over the repeats (CUDA events after a warm-up call,
// host to host), the same per scene (or per hypothesis), the ratio to batch 1 per scene and,
// for the samples, the roofline fraction: the official FLOPs (every row, as compute-budget.md
// counts them) / time / the bf16 GEMM ceiling measured in the same run. The DiTs fold a batch
// into the rows of their products, the MST its windows (docs/world-model.md); the DC-AE runs
// item by item.
// Usage: bench_gpu_batch [--repeats N] [--min-batch B] [--max-batch B] [--max-hypotheses K]
//                        [--only mst,plan,step,traj100,vis100,hyp] (step includes decode) [--profile]
// --profile: instead of the rows, one 1-step sample of each wanted DiT (traj100, vis100) at each
// batch, inside cudaProfilerStart/Stop after a warm-up (for ncu --profile-from-start off).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include <cuda_profiler_api.h>

#include "epona/core/arena.hpp"
#include "epona/core/rng.hpp"
#include "epona/flow/schedule.hpp"
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
  std::int64_t max_batch = 16, max_hypotheses = 64, min_batch = 1;
  bool profile = false;
  std::string only;  // comma-separated row kinds (mst, plan, step, decode, traj100, vis100, hyp); empty: all
  bool want(const std::string& kind) const { return only.empty() || ("," + only + ",").find("," + kind + ",") != std::string::npos; }
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
    else if (a == "--min-batch") o.min_batch = value();
    else if (a == "--profile") o.profile = true;
    else if (a == "--only") {
      EPONA_CHECK(i + 1 < argc, a, " needs a value");
      o.only = argv[++i];
    }
    else fail("unknown option '", a, "' (--repeats N, --min-batch B, --max-batch B, --max-hypotheses K, --only KINDS, --profile)");
  }
  return o;
}

using bench::median;

// A row: the call's median, per item, and per item against `single` (the batch-1 row's per item).
struct Row {
  std::string name;
  double ms = 0, per_item = 0, ratio = 0, roofline = 0;
};
// `flops`: the official FLOPs of the whole call, for its roofline fraction against `ceiling`
// (TFLOP/s); 0: none.
Row emit(const std::string& name, const std::vector<double>& runs, std::int64_t items, double single_per_item,
         double flops = 0, double ceiling = 0) {
  Row r{name, median(runs), median(runs) / double(items), 0, 0};
  r.ratio = single_per_item > 0 ? r.per_item / single_per_item : 1.0;
  if (flops > 0 && ceiling > 0) r.roofline = flops / (r.ms * 1e-3) / (ceiling * 1e12);
  std::printf("{\"name\": \"%s\", \"ms\": %.3f, \"items\": %lld, \"per_item_ms\": %.3f, \"per_item_vs_one\": %.3f, "
              "\"roofline\": %.4f}\n",
              name.c_str(), r.ms, static_cast<long long>(items), r.per_item, r.ratio, r.roofline);
  std::fflush(stdout);
  return r;
}

// One DiT's `steps`-step sample of Bt items with random conditioning (the window's shapes): the
// call's milliseconds per repeat, after one warm-up that records its graph.
template <class Time>
std::vector<double> dit_sample_times(WorldModel<Cuda, bf16>& wm, const model::FluxDiT<Cuda, bf16>& dit, bool vis,
                                     std::int64_t Bt, std::int64_t steps, const Time& time) {
  const auto& cfg = wm.config();
  auto& ctx = wm.context();
  const auto ids = model::prepare_ids(Bt, cfg.latent_h(), cfg.latent_w(), cfg.tokens_per_frame(), cfg.traj_len);
  const auto& target_ids = vis ? ids.img : ids.traj;
  const nn::JointRows rows{cfg.tokens_per_frame(), target_ids.size(1)};
  TorchGenerator gen(5);
  const auto cond = BackendTraits<Cuda>::upload(gen.randn({Bt, rows.cond, cfg.context_in_dim()}));
  const auto y = BackendTraits<Cuda>::upload(gen.randn({Bt, cfg.pose_emb_dim()}));
  const auto noise = gen.randn({Bt, rows.target, dit.config().in_channels});
  auto state = BackendTraits<Cuda>::upload(noise);
  Arena<Cuda> arena(dit.conditioning_bytes(Bt, rows) + dit.sample_bytes(Bt, rows, steps));
  const auto c = dit.prepare(ctx, arena, cond, ids.cond, target_ids, y);
  const auto grid = flow::get_schedule(steps, rows.target);
  return time(ctx, [&] { dit.sample(ctx, arena, c, grid, state); });
}

// The official FLOPs of one DiT's 100-step sample of one item (every row of every block).
double dit_sample_flops(const WorldModelConfig& cfg, const model::FluxDiT<Cuda, bf16>& dit, bool vis) {
  const nn::JointRows rows{cfg.tokens_per_frame(), vis ? cfg.img_tokens() : cfg.traj_len};
  return dit.forward_flops(rows, false).total() * double(cfg.num_sampling_steps);
}

// The MST over the window h: the call's milliseconds per repeat (stt_features and pose_emb on
// the device, the action entries of the window with its last repeated, as a self-predicted step).
template <class Time>
std::vector<double> mst_times(WorldModel<Cuda, bf16>& wm, const History& h, const Time& time) {
  const auto& cfg = wm.config();
  const std::int64_t Bt = h.latents.size(0);
  const auto indices = wm.window_indices(h, nullptr);  // (pose, yaw)
  const auto latents = BackendTraits<Cuda>::upload(h.latents);
  Tensor<float, Cuda> stt({Bt, cfg.tokens_per_frame(), cfg.n_embd}), emb({Bt, cfg.pose_emb_dim()});
  Arena<Cuda> arena(wm.mst().evaluate_workspace_bytes(Bt));
  return time(wm.context(), [&] {
    arena.reset();
    wm.mst().evaluate(wm.context(), arena, latents, indices.first, indices.second, stt, emb);
  });
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
  if (o.profile) {
    // The warm-up call records the graph; the second call replays it alone inside the profiler range.
    const auto profiled = [&](cuda::Context& c, const std::function<void()>& fn) {
      fn();
      c.synchronize();
      EPONA_CUDA_CHECK(cudaProfilerStart());
      fn();
      c.synchronize();
      EPONA_CUDA_CHECK(cudaProfilerStop());
      return std::vector<double>{};
    };
    for (std::int64_t Bt = o.min_batch; Bt <= o.max_batch; Bt *= 2) {
      if (o.want("traj100")) dit_sample_times(wm, wm.traj_dit(), false, Bt, 1, profiled);
      if (o.want("vis100")) dit_sample_times(wm, wm.vis_dit(), true, Bt, 1, profiled);
      std::printf("# profiled batch %lld\n", static_cast<long long>(Bt));
    }
    return 0;
  }
  const double ceiling = bench::gemm_ceiling_tflops(ctx);
  std::printf("# bf16 GEMM ceiling (8192^3): %.1f TFLOP/s\n", ceiling);
  const double vis_flops = dit_sample_flops(cfg, wm.vis_dit(), true), traj_flops = dit_sample_flops(cfg, wm.traj_dit(), false);
  const double mst_flops = wm.mst().evaluate_flops(false).total();
  double mst1 = 0, plan1 = 0, step1 = 0, decode1 = 0, vis1 = 0, traj1 = 0, step_decode1 = 0;
  for (std::int64_t Bt = o.min_batch; Bt <= o.max_batch; Bt *= 2) {
    const History h = window(cfg, Bt);
    const std::string b = "_b" + std::to_string(Bt);
    if (o.want("mst")) {
      rows.push_back(emit("mst" + b, mst_times(wm, h, time), Bt, mst1, mst_flops * double(Bt), ceiling));
      if (Bt == 1) mst1 = rows.back().per_item;
      if (Bt > 1) {
        const std::int64_t fold_limit = wm.mst().fold_limit();
        wm.mst().set_fold_limit(1);
        rows.push_back(emit("mst1" + b, mst_times(wm, h, time), Bt, mst1, mst_flops * double(Bt), ceiling));
        wm.mst().set_fold_limit(fold_limit);
      }
    }
    if (o.want("plan")) {
      rows.push_back(emit("plan" + b, time(ctx, [&] { (void)wm.plan(h, opt); }), Bt, plan1));
      if (Bt == 1) plan1 = rows.back().per_item;
    }
    if (o.want("step") && o.want("decode")) {
      const Row step = emit("step" + b, time(ctx, [&] { (void)wm.predict_next(h, std::nullopt, opt); }), Bt, step1);
      TorchGenerator gen(3);
      const auto z = BackendTraits<Cuda>::upload(gen.randn({Bt, dcfg.latent_channels, cfg.latent_h(), cfg.latent_w()}));
      const Row decode = emit("decode" + b, time(dctx, [&] { (void)dcae.decode(dctx, z, false); }), Bt, decode1);
      if (Bt == 1) step1 = step.per_item, decode1 = decode.per_item;
      // An AR step with its decode, per scene: the two rows' medians added (measured apart).
      const double step_decode = step.per_item + decode.per_item;
      if (Bt == 1) step_decode1 = step_decode;
      const double ratio = step_decode1 > 0 ? step_decode / step_decode1 : 1.0;
      std::printf("{\"name\": \"step_decode%s\", \"per_item_ms\": %.3f, \"per_item_vs_one\": %.3f}\n", b.c_str(),
                  step_decode, ratio);
      rows.insert(rows.end(), {step, decode, Row{"step_decode" + b, step_decode * double(Bt), step_decode, ratio, 0}});
    }
    if (o.want("traj100")) {
      rows.push_back(emit("traj100" + b, dit_sample_times(wm, wm.traj_dit(), false, Bt, cfg.num_sampling_steps, time), Bt, traj1,
                          traj_flops * double(Bt), ceiling));
      if (Bt == 1) traj1 = rows.back().per_item;
    }
    if (o.want("vis100")) {
      rows.push_back(emit("vis100" + b, dit_sample_times(wm, wm.vis_dit(), true, Bt, cfg.num_sampling_steps, time), Bt, vis1,
                          vis_flops * double(Bt), ceiling));
      if (Bt == 1) vis1 = rows.back().per_item;
    }
  }
  const History one = window(cfg, 1);
  for (std::int64_t K = 1; o.want("hyp") && K <= o.max_hypotheses; K *= 2) {
    const int before = wm.traj_dit().sampler_graph().captures();
    rows.push_back(emit("hyp_k" + std::to_string(K), time(ctx, [&] { (void)wm.plan_hypotheses(one, K, opt); }), 1,
                        plan1));
    // One recording per K (the warm-up's), replayed by the timed calls.
    const nn::JointRows traj_rows{cfg.tokens_per_frame(), cfg.traj_len};
    std::printf("# hyp_k%lld: %d TrajDiT graph recording(s), the last %.1f ms (host); TrajDiT sample %.1f MiB\n",
                static_cast<long long>(K), wm.traj_dit().sampler_graph().captures() - before,
                wm.traj_dit().sampler_graph().last_capture_ms(),
                double(wm.traj_dit().sample_bytes(K, traj_rows, cfg.num_sampling_steps)) / double(1 << 20));
  }
  std::printf("\n%-15s %12s %14s %16s %10s\n", "row", "ms / call", "ms / item", "item vs batch 1", "roofline");
  for (const Row& r : rows)
    std::printf("%-15s %12.2f %14.2f %16.3f %9.1f%%\n", r.name.c_str(), r.ms, r.per_item, r.ratio, 100 * r.roofline);
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
