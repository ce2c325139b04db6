// World-model CPU benchmarks at the "bench-mid" configuration of pytorch-baseline.md (image
// 256x512 -> 8x16 latents, 10 frames, MST 1024/8 heads/4 blocks, VisDiT 1024/8 heads 2+2,
// TrajDiT 512/4 heads 1+1; random weights): MST evaluate, one TrajDiT and one VisDiT
// evaluation (cond_in included, as the baseline's forward), float32 and bf16 weights.
// Counters: GFLOP = the official work as compute-budget.md counts it (2·M·N·K per Linear,
// 4·H·Lq·Lk·d per attention, every row of every block); GEMM_GFLOP = its GEMM part (the
// GFLOP column of pytorch-baseline.md); exec_GFLOP = what runs after the exact pruning of
// the last blocks; GFLOP/s = GFLOP / time (effective rate, comparable with PyTorch's).
#include <benchmark/benchmark.h>

#include <memory>

#include "epona/core/arena.hpp"
#include "epona/model/pose_tokenizer.hpp"
#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"

using namespace epona;

namespace {

WorldModelConfig bench_mid() {
  WorldModelConfig c;
  c.image_h = 256;
  c.image_w = 512;
  c.condition_frames = 10;
  c.n_embd = 1024;
  c.n_head = 8;
  c.n_layer = {4, 2, 2};
  c.n_embd_dit = 1024;
  c.n_head_dit = 8;
  c.axes_dim_dit = {16, 56, 56};
  c.n_layer_traj = {1, 1};
  c.n_embd_dit_traj = 512;
  c.n_head_dit_traj = 4;
  c.axes_dim_dit_traj = {16, 56, 56};
  c.traj_len = 15;
  return c;
}

Tensor<float, Cpu> random(Shape shape, std::uint64_t seed, float scale = 1.0f) {
  TorchGenerator gen(seed);
  auto t = gen.randn(std::move(shape));
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] *= scale;
  return t;
}

template <class W>
struct Bench {
  WorldModelConfig cfg = bench_mid();
  WorldModel<Cpu, W> wm = WorldModel<Cpu, W>::load(model::random_world_weights(cfg, 7), cfg);
  Tensor<float, Cpu> latents = random({1, cfg.condition_frames, cfg.img_tokens(), cfg.token_dim()}, 1);
  Tensor<float, Cpu> pose_idx = model::PoseTokenizer::from(cfg).poses_to_indices(random({1, cfg.condition_frames + 1, 2}, 2, 0.5f));
  Tensor<float, Cpu> yaw_idx = model::PoseTokenizer::from(cfg).yaws_to_indices(random({1, cfg.condition_frames + 1, 1}, 3));
  Tensor<float, Cpu> stt{1, cfg.tokens_per_frame(), cfg.n_embd}, pose_emb{1, cfg.pose_emb_dim()};
  model::DitIds ids = model::prepare_ids(1, cfg.latent_h(), cfg.latent_w(), cfg.tokens_per_frame(), cfg.traj_len);

  Bench() {
    Arena<Cpu> arena(wm.mst().evaluate_workspace_bytes());
    wm.mst().evaluate(wm.context(), arena, latents, pose_idx, yaw_idx, stt, pose_emb);
  }
  static Bench& get() {
    static Bench b;
    return b;
  }
};

void report(benchmark::State& state, const nn::Flops& official, const nn::Flops& executed, int threads) {
  state.counters["GFLOP"] = official.total() / 1e9;
  state.counters["GEMM_GFLOP"] = official.gemm / 1e9;
  state.counters["exec_GFLOP"] = executed.total() / 1e9;
  state.counters["GFLOP/s"] = benchmark::Counter(official.total() / 1e9, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["threads"] = threads;
}

template <class W>
void mst_evaluate(benchmark::State& state) {
  auto& b = Bench<W>::get();
  Arena<Cpu> arena(b.wm.mst().evaluate_workspace_bytes());
  for (auto _ : state) {
    arena.reset();
    b.wm.mst().evaluate(b.wm.context(), arena, b.latents, b.pose_idx, b.yaw_idx, b.stt, b.pose_emb);
    benchmark::DoNotOptimize(b.stt.data());
  }
  report(state, b.wm.mst().evaluate_flops(false), b.wm.mst().evaluate_flops(true), b.wm.context().threads());
}

template <class W>
void dit_forward(benchmark::State& state, bool vis) {
  auto& b = Bench<W>::get();
  const auto& dit = vis ? b.wm.vis_dit() : b.wm.traj_dit();
  const auto& x_ids = vis ? b.ids.img : b.ids.traj;
  const auto x = random({1, x_ids.size(1), dit.config().in_channels}, 4);
  Tensor<float, Cpu> v(x.shape()), t = Tensor<float, Cpu>::full({1}, 0.37f);
  const model::JointRows rows{b.cfg.tokens_per_frame(), x_ids.size(1)};
  Arena<Cpu> arena(dit.forward_bytes(1, rows));
  for (auto _ : state) {
    dit.forward(b.wm.context(), arena, x, x_ids, b.stt, b.ids.cond, t, b.pose_emb, v);
    benchmark::DoNotOptimize(v.data());
  }
  report(state, dit.forward_flops(rows, false), dit.forward_flops(rows, true), b.wm.context().threads());
}

// Argument: threads (0 = all). One thread is timed in CPU time (robust on a shared machine),
// all threads in wall-clock time.
template <class W>
void use_threads(benchmark::State& state) {
  Bench<W>::get().wm.context().set_threads(static_cast<int>(state.range(0)));
}
void BM_mst_evaluate_fp32(benchmark::State& s) { use_threads<float>(s), mst_evaluate<float>(s); }
void BM_trajdit_eval_fp32(benchmark::State& s) { use_threads<float>(s), dit_forward<float>(s, false); }
void BM_visdit_eval_fp32(benchmark::State& s) { use_threads<float>(s), dit_forward<float>(s, true); }
void BM_mst_evaluate_bf16(benchmark::State& s) { use_threads<bf16>(s), mst_evaluate<bf16>(s); }
void BM_trajdit_eval_bf16(benchmark::State& s) { use_threads<bf16>(s), dit_forward<bf16>(s, false); }
void BM_visdit_eval_bf16(benchmark::State& s) { use_threads<bf16>(s), dit_forward<bf16>(s, true); }

}  // namespace

#define EPONA_WORLD_BENCH(fn, seconds)                                                              \
  BENCHMARK(fn)->Name(#fn "/threads:1")->Arg(1)->Unit(benchmark::kMillisecond)->MinTime(seconds); \
  BENCHMARK(fn)->Name(#fn "/threads:all")->Arg(0)->Unit(benchmark::kMillisecond)->MinTime(seconds)->UseRealTime()

EPONA_WORLD_BENCH(BM_mst_evaluate_fp32, 2.0);
EPONA_WORLD_BENCH(BM_trajdit_eval_fp32, 1.0);
EPONA_WORLD_BENCH(BM_visdit_eval_fp32, 2.0);
EPONA_WORLD_BENCH(BM_mst_evaluate_bf16, 2.0);
EPONA_WORLD_BENCH(BM_trajdit_eval_bf16, 1.0);
EPONA_WORLD_BENCH(BM_visdit_eval_bf16, 2.0);

BENCHMARK_MAIN();
