// GEMM benchmarks of the CPU backend: `linear` (Eigen GEMM + fused bias/activation pass) at
// square sizes and the model's shapes, float32 and bfloat16 weights, 1 and all threads, in
// GFLOP/s; plus the measured fp32 peak (a tight loop of independent FMAs) to compare with.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <random>
#include <thread>
#include <vector>

#if defined(_OPENMP)
#include <omp.h>
#endif

#include "epona/cpu/gemm.hpp"
#include "epona/cpu/simd.hpp"

using namespace epona;
using epona::cpu::simd::Batch;

namespace {

int all_threads() { return std::max(1, static_cast<int>(std::thread::hardware_concurrency())); }

// 16 independent FMA chains per thread: more than latency (4 cycles) × throughput (2 FMA
// pipes) needs, so the loop runs at the FMA units' rate. acc = acc·m + c converges to a fixed
// point: no overflow, no denormals.
constexpr int kChains = 16;
float fma_chains(std::int64_t iters) {
  Batch acc[kChains];
  for (int c = 0; c < kChains; ++c) acc[c] = Batch(static_cast<float>(c));
  const Batch m(0.999f), add(0.001f);
  for (std::int64_t i = 0; i < iters; ++i)
    for (int c = 0; c < kChains; ++c) acc[c] = xsimd::fma(acc[c], m, add);
  Batch s(0.f);
  for (int c = 0; c < kChains; ++c) s += acc[c];
  return cpu::simd::reduce_add(s);
}

// Peak fp32 FLOP/s with `threads` threads each running the FMA loop.
void BM_PeakFma(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  constexpr std::int64_t iters = 1 << 22;
  for (auto _ : state) {
    float sink = 0;
#pragma omp parallel num_threads(threads) reduction(+ : sink)
    sink += fma_chains(iters);
    benchmark::DoNotOptimize(sink);
  }
  const double flops = 2.0 * kChains * cpu::simd::kWidth * static_cast<double>(iters) * threads;
  state.counters["GFLOPS"] = benchmark::Counter(flops * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["GFLOPS_per_core"] =
      benchmark::Counter(flops * 1e-9 / threads, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["threads"] = threads;
  state.counters["simd_width"] = static_cast<double>(cpu::simd::kWidth);
}

template <class W>
cpu::HostTensor<W> random_tensor(Shape shape, unsigned seed) {
  cpu::HostTensor<W> t(std::move(shape));
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> d(-1.f, 1.f);
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = W(d(gen));
  return t;
}

// args: M, N, K, threads, epilogue (0 none, 2 GELU-tanh), bias (0/1)
template <class W>
void BM_Linear(benchmark::State& state) {
  const std::int64_t M = state.range(0), N = state.range(1), K = state.range(2);
  const int threads = static_cast<int>(state.range(3));
  const auto epi = static_cast<cpu::Epilogue>(state.range(4));
  cpu::Context ctx(threads);
  const auto x = random_tensor<float>({M, K}, 1);
  const auto w = random_tensor<W>({N, K}, 2);
  const auto b = state.range(5) ? random_tensor<W>({N}, 3) : cpu::HostTensor<W>();
  cpu::HostTensor<float> y({M, N});
  for (auto _ : state) {
    cpu::linear(ctx, x, w, b, y, epi);
    benchmark::DoNotOptimize(y.data());
    benchmark::ClobberMemory();
  }
  state.counters["GFLOPS"] = benchmark::Counter(2.0 * M * N * K * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  // Weight bytes read per second: the figure that matters for the few-row (GEMV-like) shapes.
  state.counters["weight_GBps"] =
      benchmark::Counter(double(N * K * sizeof(W)) * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["threads"] = Eigen::nbThreads();
}

// With --benchmark_repetitions=N, also report the best repetition (min time, max rate): on a
// machine shared with other jobs the best run is the one least disturbed.
void best_of(benchmark::internal::Benchmark* b) {
  b->ComputeStatistics("min", [](const std::vector<double>& v) { return *std::min_element(v.begin(), v.end()); });
  b->ComputeStatistics("max", [](const std::vector<double>& v) { return *std::max_element(v.begin(), v.end()); });
}

void peak_args(benchmark::internal::Benchmark* b) {
  b->Arg(1);
  if (all_threads() > 1) b->Arg(all_threads());
  best_of(b);
  b->UseRealTime()->Unit(benchmark::kMillisecond);
}

void linear_args(benchmark::internal::Benchmark* b) {
  b->ArgNames({"M", "N", "K", "thr", "epi", "bias"});
  std::vector<int> thread_counts{1};
  if (all_threads() > 1) thread_counts.push_back(all_threads());
  for (int t : thread_counts) {
    for (std::int64_t s : {512, 1024, 2048}) b->Args({s, s, s, t, 0, 0});
    b->Args({5150, 2048, 2048, t, 0, 1});   // MST-sized projections (10 frames × 515 tokens)
    b->Args({5150, 8192, 2048, t, 2, 1});   // MLP up-projection + bias + GELU-tanh
    b->Args({5150, 2048, 8192, t, 0, 1});   // MLP down-projection
    b->Args({2, 12288, 2048, t, 0, 1});     // adaLN modulation (batch 2): weight-bandwidth bound
  }
  best_of(b);
  b->UseRealTime()->Unit(benchmark::kMillisecond)->MinTime(0.5);
}

void linear_bf16_args(benchmark::internal::Benchmark* b) {
  b->ArgNames({"M", "N", "K", "thr", "epi", "bias"});
  b->Args({1024, 1024, 1024, all_threads(), 0, 0});
  b->Args({5150, 2048, 2048, all_threads(), 0, 1});
  b->Args({2, 12288, 2048, 1, 0, 1});
  b->Args({2, 12288, 2048, all_threads(), 0, 1});
  best_of(b);
  b->UseRealTime()->Unit(benchmark::kMillisecond)->MinTime(0.5);
}

// The epilogue pass alone: bias + GELU-tanh over a (5150, 8192) output.
void BM_BiasGeluEpilogue(benchmark::State& state) {
  const std::int64_t M = 5150, N = 8192;
  cpu::Context ctx(static_cast<int>(state.range(0)));
  std::vector<float> y(static_cast<std::size_t>(M * N), 0.5f), b(static_cast<std::size_t>(N), 0.1f);
  for (auto _ : state) {
    cpu::detail::apply_epilogue(y.data(), N, M, N, b.data(), cpu::Epilogue::GeluTanh);
    benchmark::ClobberMemory();
  }
  state.counters["GBps"] = benchmark::Counter(2.0 * 4 * M * N * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
}

}  // namespace

BENCHMARK(BM_PeakFma)->Apply(peak_args);
BENCHMARK(BM_Linear<float>)->Name("BM_Linear_f32")->Apply(linear_args);
BENCHMARK(BM_Linear<bf16>)->Name("BM_Linear_bf16w")->Apply(linear_bf16_args);
BENCHMARK(BM_BiasGeluEpilogue)->Apply(peak_args);
BENCHMARK_MAIN();
