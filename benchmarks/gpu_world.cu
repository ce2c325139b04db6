// epona's world model on the GPU at the real configuration (512x1024 frames -> 16x32 latents,
// 10 condition frames, the shipped widths and depths, 100 sampling steps), random weights
// (model/random_weights.hpp), bf16 weights and activations (float32 MST residual stream):
// MST over 10 frames (and `mst_front`: from its start to the tokens assembled); TrajDiT and
// VisDiT one evaluation (forward: cond_in, modulations and one velocity) and 100-step sample
// (prepare + the recorded sampling loop); one autoregressive step (MST + TrajDiT 100 +
// VisDiT 100, self-predicted action, host to host); the bf16 GEMM
// ceiling through the same cuBLASLt path (8192^3, rotating buffers); device memory in use;
// the element-wise passes between the GEMMs at the model's sizes (row `pass_*`: residual add +
// LayerNorm apart and fused, in-place LayerNorm, the erf GELU, gated residual + modulated norm).
// CUDA events around each call after warm-up; medians. One JSON object per line (the
// side-by-side harness reads them), then a readable table.
// Usage: bench_gpu_world [--repeats N] [--steps S] [--only a,b,...] [--fp32] [--profile]
// (--only names: gemm, passes, dit_gemms, mst, traj_eval, traj_sample, vis_eval, vis_sample, step;
// dit_gemms: the double blocks' per-stream products serial, on two streams, and batched, and for
// the VisDiT the batched product over the target's 512 rows with the condition's 3 more apart;
// --profile: one eager evaluation of each DiT (and, with mst wanted, one MST evaluation)
// between cudaProfilerStart/Stop, for ncu;
// --tune-compare: the DiT rows again with the cuBLASLt candidate timing switched, suffixed;
// --residual-compare: the MST again with the residual add in its GEMMs off and on, two rounds;
// --qk-norm-compare: the same with the time layers' QK LayerNorm inside their attention;
// --pdl-compare: the MST and the DiT rows with programmatic dependent launches off and on, two
// rounds; --front-compare: the TrajDiT sample with its pipelined condition front off and on,
// FluxDiT::SamplerOptions, two rounds; --order-compare: the MST with its large row passes
// walking the rows first to last and last to first, two rounds; --group-compare: the MST with
// its key, value and query products one grouped product or three (policy().pair_gemm), two rounds;
// --mst-tune-compare: the MST with its large products' cuBLASLt candidates timed or not;
// --sampler-compare SOLVER:PLAN:VIDEO (e.g. midpoint:10:10, `epona --sampler fast`): the step row
// again with that flow solver and those planner / video steps, alternating with the official
// sampler over two rounds, rows step_official_rN and step_SOLVER_PLAN_VIDEO_rN; docs/solvers.md);
// --rollout-compare N: rollouts of N frames, each step followed by the DC-AE decode of its frame
// (the real DC-AE, random weights, its own stream): `serial` decodes after each step on the host
// thread, `beside` on a worker thread while the next step samples (as the epona program's
// rollouts do, apps/epona/rollout_common.hpp); host wall time per frame over the rollout, median
// of 3, two rounds, with the official sampler and with --sampler-compare's; rows
// rollout_{serial,beside}_{official,SOLVER_PLAN_VIDEO}_rN (issue #40).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <future>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <cuda_profiler_api.h>

#include "epona/core/rng.hpp"
#include "epona/cuda/backend.cuh"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/model/pose_tokenizer.hpp"
#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"
#include "bench_stats.hpp"
#include "gpu_event_timer.cuh"
#include "gpu_frame_decode.cuh"

using namespace epona;

namespace {

struct Options {
  int repeats = 10;
  std::int64_t steps = 100;
  std::set<std::string> only;
  bool fp32 = false;
  bool profile = false;  // one eager evaluation of each DiT inside cudaProfilerStart/Stop
  bool tune_compare = false;  // the DiT rows again with the GEMM tuning switched
  bool residual_compare = false;  // the MST with the residual add in the GEMM off and on, two rounds
  bool qk_norm_compare = false;   // the MST with the time layers' QK LayerNorm inside the attention off and on
  bool pdl_compare = false;       // the MST and the DiTs with programmatic dependent launches off and on
  bool front_compare = false;     // the TrajDiT sample with its pipelined condition front off and on
  bool order_compare = false;     // the MST with its large row passes in forward and reverse row order
  bool group_compare = false;     // the MST with its key, value and query products grouped or not
  bool mst_tune_compare = false;  // the MST with its large products' cuBLASLt candidates timed or not
  std::int64_t rollout_frames = 0;  // --rollout-compare N: N-frame rollouts with the DC-AE decode, serial and beside
  std::optional<DitSamplers> sampler_compare;  // the step again with these solvers and steps
  std::string sampler_name;                    // its row suffix, SOLVER_PLAN_VIDEO
  bool want(const std::string& n) const { return only.empty() || only.count(n) > 0; }
};

// For `ncu --profile-from-start off`: `fn` (already run once, so its plans and tables exist)
// once more, alone inside cudaProfilerStart/Stop.
void profile_once(cuda::Context& ctx, const std::function<void()>& fn) {
  ctx.synchronize();
  EPONA_CUDA_CHECK(cudaProfilerStart());
  fn();
  ctx.synchronize();
  EPONA_CUDA_CHECK(cudaProfilerStop());
}

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const auto next = [&]() -> std::string {
      EPONA_CHECK(i + 1 < argc, "missing value after ", a);
      return argv[++i];
    };
    if (a == "--repeats") o.repeats = std::stoi(next());
    else if (a == "--steps") o.steps = std::stoll(next());
    else if (a == "--fp32") o.fp32 = true;
    else if (a == "--profile") o.profile = true;
    else if (a == "--tune-compare") o.tune_compare = true;
    else if (a == "--residual-compare") o.residual_compare = true;
    else if (a == "--qk-norm-compare") o.qk_norm_compare = true;
    else if (a == "--pdl-compare") o.pdl_compare = true;
    else if (a == "--front-compare") o.front_compare = true;
    else if (a == "--order-compare") o.order_compare = true;
    else if (a == "--group-compare") o.group_compare = true;
    else if (a == "--mst-tune-compare") o.mst_tune_compare = true;
    else if (a == "--rollout-compare") o.rollout_frames = std::max<std::int64_t>(2, std::stoll(next()));
    else if (a == "--sampler-compare") {
      std::stringstream ss(next());
      std::string solver, plan, video;
      EPONA_CHECK(std::getline(ss, solver, ':') && std::getline(ss, plan, ':') && std::getline(ss, video),
                  "--sampler-compare needs SOLVER:PLAN_STEPS:VIDEO_STEPS, e.g. midpoint:10:10");
      const auto kind = flow::parse_solver(solver);
      o.sampler_compare = DitSamplers{{kind, std::stoll(plan)}, {kind, std::stoll(video)}};
      check_samplers(*o.sampler_compare);
      o.sampler_name = solver + "_" + plan + "_" + video;
    }
    else if (a == "--only") {
      std::stringstream ss(next());
      for (std::string s; std::getline(ss, s, ',');) o.only.insert(s);
    } else fail("unknown option ", a,
                " (--repeats N, --steps S, --only a,b, --fp32, --profile, --tune-compare, --residual-compare, "
                "--qk-norm-compare, --pdl-compare, --front-compare, --order-compare, --group-compare, "
                "--mst-tune-compare, --sampler-compare SOLVER:PLAN:VIDEO, --rollout-compare FRAMES)");
  }
  return o;
}

using bench::median;

using bench::event_times_ms;
using bench::gemm_ceiling_tflops;


void emit(const std::string& name, const std::vector<double>& runs, double tflop) {
  std::printf("{\"name\": \"%s\", \"ms\": %.4f, \"tflop\": %.6f, \"runs\": [", name.c_str(), median(runs), tflop);
  for (std::size_t i = 0; i < runs.size(); ++i) std::printf("%s%.4f", i ? ", " : "", runs[i]);
  std::printf("]}\n");
  std::fflush(stdout);
}
void emit_value(const std::string& name, double value) {
  std::printf("{\"name\": \"%s\", \"value\": %.6f}\n", name.c_str(), value);
  std::fflush(stdout);
}

// The MST's front: from the start of an evaluation to its tokens assembled (an observer records
// an event when it sees "tokens_in"; observed evaluations run every block unpruned, after the
// front). `evaluate(observer)` runs one evaluation. Three warm-up runs, then `repeats`.
template <class Evaluate>
std::vector<double> mst_front_times_ms(cuda::Context& ctx, int repeats, const Evaluate& evaluate) {
  cudaEvent_t start = nullptr, tokens = nullptr;
  EPONA_CUDA_CHECK(cudaEventCreate(&start));
  EPONA_CUDA_CHECK(cudaEventCreate(&tokens));
  std::vector<double> runs;
  for (int r = 0; r < repeats + 3; ++r) {
    EPONA_CUDA_CHECK(cudaEventRecord(start, ctx.stream()));
    evaluate([&](std::int64_t, const std::string& what, const Tensor<float, Cuda>&) {
      if (what == "tokens_in") EPONA_CUDA_CHECK(cudaEventRecord(tokens, ctx.stream()));
    });
    EPONA_CUDA_CHECK(cudaEventSynchronize(tokens));
    float ms = 0;
    EPONA_CUDA_CHECK(cudaEventElapsedTime(&ms, start, tokens));
    if (r >= 3) runs.push_back(ms);
  }
  EPONA_CUDA_CHECK(cudaEventDestroy(start));
  EPONA_CUDA_CHECK(cudaEventDestroy(tokens));
  return runs;
}

std::size_t used_device_bytes() {
  std::size_t free_b = 0, total_b = 0;
  EPONA_CUDA_CHECK(cudaMemGetInfo(&free_b, &total_b));
  return total_b - free_b;
}

// A device tensor of standard normal values rounded to T.
template <class T>
Tensor<T, Cuda> random_device(cuda::Context& ctx, Shape shape, std::uint64_t seed) {
  TorchGenerator gen(seed);
  const auto host = gen.randn(std::move(shape));
  Tensor<T, Cpu> h(host.shape());
  for (std::int64_t i = 0; i < h.numel(); ++i) h.data()[i] = T(host.data()[i]);
  return cuda::to_device(ctx, h);
}

// The element-wise passes between the GEMMs, at the sizes the model runs them (GB/s counts
// each operand read once and each result written once).
void time_passes(cuda::Context& ctx, int repeats) {
  const std::int64_t rows = 5150, C = 2048, hidden = 4 * C;  // the MST's F·T tokens
  auto x = random_device<float>(ctx, {rows, C}, 1);
  auto y = random_device<bf16>(ctx, {rows, C}, 2), u = random_device<bf16>(ctx, {rows, C}, 3);
  auto h = random_device<bf16>(ctx, {rows, hidden}, 4);
  auto w = random_device<float>(ctx, {C}, 5), b = random_device<float>(ctx, {C}, 6);
  const auto pass = [&](const std::string& name, double bytes, const std::function<void()>& fn) {
    const auto runs = event_times_ms(ctx, repeats, 3, fn);
    emit("pass_" + name, runs, 0);
    std::printf("# pass_%s: %.1f us, %.0f GB/s\n", name.c_str(), 1e3 * median(runs), bytes / (median(runs) * 1e6));
  };
  const double f32 = 4.0 * rows * C, b16 = 2.0 * rows * C;
  pass("mst_add_then_ln", 3 * f32 + 2 * b16, [&] {
    cuda::add_inplace(ctx, x.data(), y.data(), rows * C);
    cuda::layer_norm(ctx, x.data(), u.data(), rows, C, w.data(), b.data(), 1e-5f);
  });
  pass("mst_add_ln_fused", 2 * f32 + 2 * b16,
       [&] { cuda::add_layer_norm(ctx, x.data(), y.data(), u.data(), rows, C, w.data(), b.data(), 1e-5f); });
  pass("mst_ln_bf16_inplace", 2 * b16,
       [&] { cuda::layer_norm(ctx, u.data(), u.data(), rows, C, w.data(), b.data(), 1e-5f); });
  pass("mst_gelu_erf", 2.0 * 2 * rows * hidden, [&] { cuda::gelu_erf(ctx, h.data(), rows * hidden); });
  // The same pass as the GEMM's erf-GELU epilogue runs it (gemm.cuh: for_each over rows).
  pass("mst_gelu_erf_gemm_pass", 2.0 * 2 * rows * hidden, [&] {
    cuda::detail::bias_activation(ctx, h.data(), hidden, rows, hidden, static_cast<const bf16*>(nullptr),
                                  cuda::detail::GeluErfOp{});
  });
  // The TrajDiT's condition rows: gated residual, then the modulated norm.
  const std::int64_t r2 = 515, D = 1024;
  auto z = random_device<bf16>(ctx, {r2, D}, 7), sub = random_device<bf16>(ctx, {r2, D}, 8);
  auto mo = random_device<bf16>(ctx, {r2, D}, 9), mv = random_device<bf16>(ctx, {6, D}, 10);
  const double t16 = 2.0 * r2 * D;
  pass("traj_gate_then_mod", 5 * t16, [&] {
    cuda::add_gated(ctx, z.data(), sub.data(), mv.data() + 2 * D, r2, D);
    cuda::layer_norm_modulate(ctx, z.data(), mo.data(), r2, D, mv.data(), mv.data() + D, 1e-6f);
  });
  pass("traj_gate_mod_fused", 4 * t16, [&] {
    cuda::add_gated_layer_norm_modulate(ctx, z.data(), sub.data(), mv.data() + 2 * D, mo.data(), r2, D, mv.data(),
                                        mv.data() + D, 1e-6f);
  });
}

// The double blocks' per-stream products (condition rows, target rows) three ways: in sequence
// on one stream, on two streams (the model with EPONA_CUDA_PAIR_GEMM=0), and as one batch-2
// strided product (cuda::linear_batched, both items on the condition stream's rows: what the
// VisDiT's paired path runs). Row `dit_gemm_<dit>_<layer>_<how>`.
void time_stream_gemms(cuda::Context& ctx, int repeats) {
  cuda::Context side;
  cudaEvent_t fork, join;
  EPONA_CUDA_CHECK(cudaEventCreateWithFlags(&fork, cudaEventDisableTiming));
  EPONA_CUDA_CHECK(cudaEventCreateWithFlags(&join, cudaEventDisableTiming));
  struct Shape3 {
    const char* name;
    std::int64_t N, K;
    bool gelu;
  };
  for (const bool vis : {true, false}) {
    const std::int64_t D = vis ? 2048 : 1024, Mc = 515, Mt = vis ? 512 : 15;
    for (const Shape3& sh : {Shape3{"qkv", 3 * D, D, false}, Shape3{"proj", D, D, false},
                             Shape3{"fc1", 4 * D, D, true}, Shape3{"fc2", D, 4 * D, false}}) {
      auto x = random_device<bf16>(ctx, {2 * Mc, sh.K}, 11), w = random_device<bf16>(ctx, {2 * sh.N, sh.K}, 12);
      auto bias = random_device<bf16>(ctx, {2 * sh.N}, 13);
      Tensor<bf16, Cuda> y({2 * Mc, sh.N});
      const auto epi = sh.gelu ? cuda::Epilogue::GeluTanh : cuda::Epilogue::None;
      const auto one = [&](cuda::Context& c, int s, std::int64_t M) {
        cuda::linear(c, x.data() + s * Mc * sh.K, sh.K, w.data() + s * sh.N * sh.K, bias.data() + s * sh.N,
                     y.data() + s * Mc * sh.N, sh.N, M, sh.N, sh.K, epi);
      };
      const std::string tag = std::string("dit_gemm_") + (vis ? "vis_" : "traj_") + sh.name;
      // `rows`: the useful rows of each of the two streams the timed work covers
      const auto report_rows = [&](const std::string& how, std::int64_t rows_c, std::int64_t rows_t,
                                   const std::function<void()>& fn) {
        const double work = 2.0 * (rows_c + rows_t) * sh.N * sh.K / 1e12;
        const auto runs = event_times_ms(ctx, repeats, 3, fn);
        emit(tag + "_" + how, runs, work);
        std::printf("# %s_%s: %.1f us, %.0f TFLOP/s (useful rows %lld + %lld)\n", tag.c_str(), how.c_str(),
                    1e3 * median(runs), work / (median(runs) * 1e-3), static_cast<long long>(rows_c),
                    static_cast<long long>(rows_t));
      };
      const auto report = [&](const std::string& how, const std::function<void()>& fn) { report_rows(how, Mc, Mt, fn); };
      report("serial", [&] { one(ctx, 0, Mc), one(ctx, 1, Mt); });
      // on_side on the side stream beside on_main on ctx's, both inside the timed span
      const auto beside = [&](const std::function<void()>& on_side, const std::function<void()>& on_main) {
        EPONA_CUDA_CHECK(cudaEventRecord(fork, ctx.stream()));
        EPONA_CUDA_CHECK(cudaStreamWaitEvent(side.stream(), fork, 0));
        on_side();
        on_main();
        EPONA_CUDA_CHECK(cudaEventRecord(join, side.stream()));
        EPONA_CUDA_CHECK(cudaStreamWaitEvent(ctx.stream(), join, 0));
      };
      report("two_streams", [&] { beside([&] { one(side, 0, Mc); }, [&] { one(ctx, 1, Mt); }); });
      const auto batched = [&](std::int64_t rows) {
        cuda::linear_batched(ctx, x.data(), sh.K, w.data(), bias.data(), y.data(), sh.N, rows, sh.N, sh.K,
                             cuda::GemmBatch{2, Mc * sh.K, sh.N * sh.K, sh.N, Mc * sh.N}, epi);
      };
      report("batched", [&] { batched(Mc); });
      if (vis) {
        // Whether the condition stream's rows past the target's (515 - 512 = 3) cost more as the
        // batched product's fifth row tile than as a product of their own.
        const std::int64_t tail = Mc - Mt;
        const auto tail_rows = [&](cuda::Context& c) {
          cuda::linear(c, x.data() + Mt * sh.K, sh.K, w.data(), bias.data(), y.data() + Mt * sh.N, sh.N, tail, sh.N,
                       sh.K, epi);
        };
        report_rows("batched_target_rows", Mt, Mt, [&] { batched(Mt); });
        report_rows("tail_rows", tail, 0, [&] { tail_rows(ctx); });
        report("batched_target_rows_then_tail", [&] { batched(Mt), tail_rows(ctx); });
        report("batched_target_rows_tail_beside", [&] { beside([&] { tail_rows(side); }, [&] { batched(Mt); }); });
      }
    }
  }
  EPONA_CUDA_CHECK(cudaEventDestroy(fork));
  EPONA_CUDA_CHECK(cudaEventDestroy(join));
}

// Rollouts of o.rollout_frames frames with each frame's DC-AE decode (the real DC-AE, random
// weights, its own context and stream): after the step on this thread (`serial`) or on a worker
// thread while the next step samples (`beside`). Milliseconds per frame of host wall time.
template <class W>
void time_rollouts(const Options& o, WorldModel<Cuda, W>& wm, const History& h) {
  bench::FrameDecode<W> frame_decode(wm.config());
  const auto decode = [&](const Tensor<float>& tokens) { return frame_decode(tokens); };
  const auto rollout_ms = [&](const SampleOptions& opt, bool beside) {
    const auto t0 = std::chrono::steady_clock::now();
    std::future<Tensor<float>> running;
    for (std::int64_t f = 0; f < o.rollout_frames; ++f) {
      const StepResult r = wm.predict_next(h, std::nullopt, opt);
      if (running.valid()) running.get();
      if (beside)
        running = std::async(std::launch::async, decode, r.latent);
      else
        (void)decode(r.latent);
    }
    if (running.valid()) running.get();
    return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() /
           double(o.rollout_frames);
  };
  std::vector<std::pair<std::string, SampleOptions>> samplers{{"official", {}}};
  if (o.sampler_compare) {
    SampleOptions s;
    s.plan_solver = o.sampler_compare->plan.kind, s.plan_steps = o.sampler_compare->plan.steps;
    s.video_solver = o.sampler_compare->video.kind, s.video_steps = o.sampler_compare->video.steps;
    samplers.emplace_back(o.sampler_name, s);
  }
  for (auto& [name, opt] : samplers) {
    opt.seed = 7;
    (void)decode(wm.predict_next(h, std::nullopt, opt).latent);  // records the graphs, plans the decode
    for (const char* round : {"_r1", "_r2"})
      for (const bool beside : {false, true}) {
        std::vector<double> runs;
        for (int k = 0; k < 3; ++k) runs.push_back(rollout_ms(opt, beside));
        emit(std::string("rollout_") + (beside ? "beside_" : "serial_") + name + round, runs, 0);
      }
  }
}

template <class W>
int run(const Options& o) {
  WorldModelConfig cfg;  // the shipped configuration
  cfg.num_sampling_steps = o.steps;
  cuda::Context probe;
  const auto& info = probe.info();
  int driver = 0, runtime = 0;
  cudaDriverGetVersion(&driver);
  cudaRuntimeGetVersion(&runtime);
  std::printf("# device: %s, %d SMs, sm_%d%d, %.1f GiB; driver %d, runtime %d; weights %s\n", info.name.c_str(),
              info.multiprocessors, info.major, info.minor, info.global_bytes / 1073741824.0, driver, runtime,
              std::is_same_v<W, float> ? "float32" : "bf16");
  // The double blocks' path (EPONA_CUDA_PAIR_GEMM), so side-by-side runs tell their rows apart.
  std::printf("# double blocks: %s products\n", cuda::pair_gemm_enabled(probe) ? "paired" : "per-stream");
  emit_value("pair_gemm", cuda::pair_gemm_enabled(probe) ? 1 : 0);
  const double ceiling = o.want("gemm") ? gemm_ceiling_tflops(probe) : 0;
  if (ceiling > 0) emit_value("gemm_tflops", ceiling);
  if (o.want("passes")) time_passes(probe, std::max(o.repeats, 20));
  if (o.want("dit_gemms") && !std::is_same_v<W, float>) time_stream_gemms(probe, std::max(o.repeats, 20));

  const std::size_t base_bytes = used_device_bytes();
  const auto t0 = std::chrono::steady_clock::now();
  auto wm = [&] {
    const auto weights = model::random_world_weights(cfg, 1);
    return WorldModel<Cuda, W>::load(weights, cfg);
  }();
  std::printf("# random weights generated, converted and uploaded in %.1f s\n",
              std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  auto& ctx = wm.context();
  const std::int64_t F = cfg.condition_frames, L = cfg.img_tokens();
  TorchGenerator gen(0);
  const auto tok = model::PoseTokenizer::from(cfg);
  History h{gen.randn({1, F, L, cfg.token_dim()}), gen.randn({1, F, 2}), gen.randn({1, F, 1})};
  for (std::int64_t f = 0; f < F; ++f) h.rel_pose.at(0, f, 0) = 2.0f + 0.5f * h.rel_pose.at(0, f, 0);  // driving forward
  Tensor<float, Cpu> pose_full({1, F + 1, 2}), yaw_full({1, F + 1, 1});
  for (std::int64_t f = 0; f <= F; ++f) {
    const std::int64_t src = std::min(f, F - 1);
    pose_full.at(0, f, 0) = h.rel_pose.at(0, src, 0);
    pose_full.at(0, f, 1) = h.rel_pose.at(0, src, 1);
    yaw_full.at(0, f, 0) = h.rel_yaw.at(0, src, 0);
  }
  const auto pose_idx = tok.poses_to_indices(pose_full), yaw_idx = tok.yaws_to_indices(yaw_full);
  const auto& mst = wm.mst();
  const auto ids = model::prepare_ids(1, cfg.latent_h(), cfg.latent_w(), cfg.tokens_per_frame(), cfg.traj_len);
  const nn::JointRows traj_rows{cfg.tokens_per_frame(), cfg.traj_len}, img_rows{cfg.tokens_per_frame(), L};
  const auto& traj = wm.traj_dit();
  const auto& vis = wm.vis_dit();
  // One arena for the component timings, sized for the largest of them.
  const std::size_t bytes = std::max({mst.evaluate_workspace_bytes(), traj.forward_bytes(1, traj_rows),
                                      traj.conditioning_bytes(1, traj_rows) + traj.sample_bytes(1, traj_rows, o.steps),
                                      vis.forward_bytes(1, img_rows),
                                      vis.conditioning_bytes(1, img_rows) + vis.sample_bytes(1, img_rows, o.steps)});
  Arena<Cuda> arena(bytes);
  const auto latents = cuda::to_device(ctx, h.latents);
  Tensor<float, Cuda> stt({1, cfg.tokens_per_frame(), cfg.n_embd}), pose_emb({1, cfg.pose_emb_dim()});
  const int R = o.repeats;
  const double mst_tflop = mst.evaluate_flops(false).total() / 1e12;
  const auto mst_once = [&] {
    arena.reset();
    mst.evaluate(ctx, arena, latents, pose_idx, yaw_idx, stt, pose_emb);
  };
  mst_once();
  if (o.profile && o.want("mst")) profile_once(ctx, mst_once);
  if (o.want("mst")) emit("mst", event_times_ms(ctx, R, 3, mst_once), mst_tflop);
  if (o.want("mst")) emit("mst_front", mst_front_times_ms(ctx, R, [&](const model::MstObserver<Cuda>& observe) {
                            arena.reset();
                            mst.evaluate(ctx, arena, latents, pose_idx, yaw_idx, stt, pose_emb, observe);
                          }), 0);
  // The MST again with one switch off and on, twice (off, on, off, on: drift shows as a round
  // difference), then the switch as it was.
  // Rounds of the MST with one choice of the context's kernel policy off and on (set(policy,
  // on)), then the policy as it was.
  const auto mst_switch_rounds = [&](const std::string& what, const auto& set) {
    const cuda::KernelPolicy was = ctx.policy();
    for (const char* round : {"_r1", "_r2"})
      for (const bool on : {false, true}) {
        set(ctx.policy(), on);
        mst_once();
        emit("mst_" + what + (on ? "_on" : "_off") + round, event_times_ms(ctx, R, 3, mst_once), mst_tflop);
      }
    ctx.policy() = was;
  };
  using Policy = cuda::KernelPolicy;
  if (o.residual_compare && o.want("mst"))
    mst_switch_rounds("residual_gemm", [](Policy& p, bool on) { p.residual_gemm = on; });
  if (o.qk_norm_compare && o.want("mst"))
    mst_switch_rounds("qk_norm_attention", [](Policy& p, bool on) { p.attention_qk_norm = on; });
  if (o.pdl_compare && o.want("mst"))
    mst_switch_rounds("pdl", [](Policy& p, bool on) { p.programmatic_launch = on; });
  if (o.order_compare && o.want("mst"))
    mst_switch_rounds("reverse_passes", [](Policy& p, bool on) { p.reversed_passes = on; });
  if (o.group_compare && o.want("mst"))
    mst_switch_rounds("grouped_kvq", [](Policy& p, bool on) { p.pair_gemm = on; });
  if (o.mst_tune_compare && o.want("mst"))
    mst_switch_rounds("gemm_tuning", [](Policy& p, bool on) {
      p.gemm_tuning = on ? cuda::GemmTuning::Large : cuda::GemmTuning::Off;
    });

  const auto dit_rows = [&](bool is_vis) -> const nn::JointRows& { return is_vis ? img_rows : traj_rows; };
  // The DiT rows; `suffix` names a second pass with the GEMM tuning switched (--tune-compare).
  // traj_sample_only: the TrajDiT sample row alone (--front-compare).
  const auto time_dits = [&](const std::string& suffix, bool traj_sample_only = false) {
    for (const bool is_vis : {false, true}) {
      if (traj_sample_only && is_vis) continue;
      const auto& dit = is_vis ? vis : traj;
      const std::string name = std::string(is_vis ? "vis" : "traj");
      const auto& rows = dit_rows(is_vis);
      const auto& target_ids = is_vis ? ids.img : ids.traj;
      const auto x0 = gen.randn({1, rows.target, is_vis ? cfg.token_dim() : std::int64_t{3}});
      const auto x = cuda::to_device(ctx, x0);
      Tensor<W, Cuda> v(x.shape());
      Tensor<float, Cpu> t({1});
      t.data()[0] = 0.3f;
      const double eval_tflop = dit.forward_flops(rows, false).total() / 1e12;
      const auto eval_once = [&] {
        arena.reset();
        dit.forward(ctx, arena, x, target_ids, stt, ids.cond, t, pose_emb, v);
      };
      // The kernels of one evaluation, prepare included (each range starts with the conversion
      // of the condition, a 515-block float -> bf16 map).
      if (o.profile && suffix.empty()) {
        eval_once();  // plans made, outside the range
        profile_once(ctx, eval_once);
      }
      if (o.want(name + "_eval") && !traj_sample_only) emit(name + "_eval" + suffix, event_times_ms(ctx, std::max(R, 20), 3, eval_once), eval_tflop);
      const auto grid = flow::get_schedule(o.steps, rows.target);
      Tensor<float, Cuda> state(x.shape());
      const auto sample_once = [&] {
        arena.reset();
        cuda::copy(ctx, x.data(), state.data(), x.numel());  // the same noise every run
        const auto c = dit.prepare(ctx, arena, stt, ids.cond, target_ids, pose_emb);
        dit.sample(ctx, arena, c, grid, state);
      };
      sample_once();  // records the sampling graph
      const auto& counts = dit.sampler_graph().node_counts();
      std::printf("# %s sampler graph: %d capture(s), last %.1f ms (host, capture + instantiate); %zu nodes: %zu kernels "
                  "(%.2f per step), %zu copies/sets\n",
                  name.c_str(), dit.sampler_graph().captures(), dit.sampler_graph().last_capture_ms(), counts.nodes,
                  counts.kernels, double(counts.kernels) / double(o.steps), counts.copies);
      emit_value(name + "_graph_kernels_per_step" + suffix, double(counts.kernels) / double(o.steps));
      if (o.want(name + "_sample"))
        emit(name + "_sample" + suffix, event_times_ms(ctx, std::max(3, R / 2), 1, sample_once), eval_tflop * double(o.steps));
    }
  };
  time_dits("");
  if (o.pdl_compare) {  // off, on, off, on (drift shows as a round difference), then as it was
    const bool was_on = ctx.policy().programmatic_launch;
    for (const char* round : {"_r1", "_r2"})
      for (const bool on : {false, true}) {
        ctx.policy().programmatic_launch = on;
        traj.reset_sampler_graph();  // the recorded loops hold the launches of the switch's old state
        vis.reset_sampler_graph();
        time_dits(std::string("_pdl") + (on ? "_on" : "_off") + round);
      }
    ctx.policy().programmatic_launch = was_on;
    traj.reset_sampler_graph();
    vis.reset_sampler_graph();
  }
  if (o.front_compare) {  // off, on, off, on (drift shows as a round difference), then as it was
    const auto was = traj.sampler_options();
    for (const char* round : {"_r1", "_r2"})
      for (const bool on : {false, true}) {
        traj.set_sampler_options({on});
        time_dits(std::string("_pipelined_") + (on ? "on" : "off") + round, true);
      }
    traj.set_sampler_options(was);
  }
  const auto time_step = [&](const std::string& suffix) {
    if (!o.want("step")) return;
    SampleOptions opt;
    opt.seed = 7;
    const double step_tflop = mst_tflop + double(o.steps) * (traj.forward_flops(traj_rows, false).total() +
                                                             vis.forward_flops(img_rows, false).total()) / 1e12;
    emit("step" + suffix, event_times_ms(ctx, std::max(3, R / 2), 1, [&] { (void)wm.predict_next(h, std::nullopt, opt); }),
         step_tflop);
  };
  // The step with another sampler, alternating with the official one (drift shows as a round
  // difference); FLOPs from each DiT's evaluation count.
  const auto time_step_samplers = [&] {
    for (const char* round : {"_r1", "_r2"})
      for (const bool other : {false, true}) {
        SampleOptions opt;
        opt.seed = 7;
        std::int64_t plan_evals = o.steps, video_evals = o.steps;
        if (other) {
          const auto& s = *o.sampler_compare;
          opt.plan_solver = s.plan.kind, opt.plan_steps = s.plan.steps;
          opt.video_solver = s.video.kind, opt.video_steps = s.video.steps;
          plan_evals = s.plan.evaluations(), video_evals = s.video.evaluations();
        }
        const double tflop = mst_tflop + (double(plan_evals) * traj.forward_flops(traj_rows, false).total() +
                                          double(video_evals) * vis.forward_flops(img_rows, false).total()) / 1e12;
        (void)wm.predict_next(h, std::nullopt, opt);  // records this setting's sampler graphs
        emit(std::string("step_") + (other ? o.sampler_name : "official") + round,
             event_times_ms(ctx, std::max(3, R / 2), 1, [&] { (void)wm.predict_next(h, std::nullopt, opt); }), tflop);
      }
  };
  if (!o.tune_compare) {
    arena = Arena<Cuda>();  // the step uses the model's own arena
    time_step("");
    if (o.sampler_compare && o.want("step")) time_step_samplers();
  } else {  // the component arena stays (the memory row then counts it too)
    time_step("");
    const auto was = ctx.policy().gemm_tuning;
    const bool tuned = was != cuda::GemmTuning::All;  // every product timed, or none
    ctx.policy().gemm_tuning = tuned ? cuda::GemmTuning::All : cuda::GemmTuning::Off;
    traj.reset_sampler_graph();
    vis.reset_sampler_graph();
    std::printf("# GEMM tuning %s for the rows suffixed _%s\n", tuned ? "on" : "off", tuned ? "tuned" : "untuned");
    const std::string suffix = tuned ? "_tuned" : "_untuned";
    time_dits(suffix);
    time_step(suffix);
    ctx.policy().gemm_tuning = was;
    arena = Arena<Cuda>();
  }
  if (o.rollout_frames > 0) time_rollouts(o, wm, h);
  emit_value("device_memory_gib", double(used_device_bytes() - base_bytes) / 1073741824.0);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Options o = parse(argc, argv);
    if (!cuda::has_gpu()) {
      std::printf("no CUDA device: nothing to measure\n");
      return 0;
    }
    return o.fp32 ? run<float>(o) : run<bf16>(o);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_gpu_world: %s\n", e.what());
    return 1;
  }
}
