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

#include "bench_mid_world.hpp"
#include "epona/core/arena.hpp"
#include "epona/model/world_model.hpp"

using namespace epona;

namespace {

template <class W>
struct Bench : bench::BenchMidWorld<W> {
  Bench() { this->evaluate_mst(); }
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
  const auto x = b.dit_input(vis);
  Tensor<float, Cpu> v(x.shape()), t = Tensor<float, Cpu>::full({1}, 0.37f);
  const nn::JointRows rows{b.cfg.tokens_per_frame(), x_ids.size(1)};
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
