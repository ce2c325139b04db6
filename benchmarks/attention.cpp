// Attention benchmarks of the CPU backend: the tiled online-softmax kernel at the model's
// shapes (MST spatial and temporal, VisDiT and TrajDiT joint attention; bench-mid and full
// sizes), 1 and all threads, in GFLOP/s (4·D FLOPs per visible query-key pair), next to the
// one-row-at-a-time scalar loop it replaced (the first reference version) for scale.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <thread>
#include <vector>

#include "epona/cpu/attention.hpp"

using namespace epona;

namespace {

struct Case {
  const char* name;
  std::int64_t seqs, heads, lq, lk;
  bool causal;
  bool time_strides;  // MST temporal: sequences are tokens (stride C), rows are frames (stride T·C)
};
constexpr std::int64_t kD = 128;
const Case kCases[] = {
    {"mst_spatial_mid", 10, 8, 131, 131, false, false},    // bench-mid: 10 frames × 131 tokens, 8 heads
    {"mst_temporal_mid", 131, 8, 10, 10, true, true},
    {"mst_spatial", 10, 16, 515, 515, false, false},       // full size: 10 frames × 515 tokens, 16 heads
    {"mst_temporal", 515, 16, 10, 10, true, true},
    {"visdit_joint", 1, 16, 1027, 1027, false, false},     // 515 condition + 512 image tokens
    {"trajdit_joint", 1, 8, 530, 530, false, false},       // 515 condition + 15 waypoints
};

struct Problem {
  std::vector<float> q, k, v, o;
  cpu::AttentionShape a;
  double flops;
  explicit Problem(const Case& c) {
    const std::int64_t C = c.heads * kD, n = c.seqs * c.lq * C;
    std::mt19937 gen(1);
    std::uniform_real_distribution<float> d(-1.f, 1.f);
    for (auto* buf : {&q, &k, &v}) {
      buf->resize(static_cast<std::size_t>(n));
      for (auto& x : *buf) x = d(gen);
    }
    o.resize(static_cast<std::size_t>(n));
    a.seqs = c.seqs, a.heads = c.heads, a.lq = c.lq, a.lk = c.lk, a.head_dim = kD;
    const std::int64_t seq = c.time_strides ? C : c.lq * C, row = c.time_strides ? c.seqs * C : C;
    a.q_seq = a.k_seq = a.v_seq = a.o_seq = seq;
    a.q_row = a.k_row = a.v_row = a.o_row = row;
    a.mask = c.causal ? cpu::Mask::Causal : cpu::Mask::None;
    const double pairs = c.causal ? c.lq * (c.lq + 1) / 2.0 : double(c.lq) * double(c.lk);
    flops = 4.0 * kD * pairs * double(c.seqs * c.heads);
  }
};

// The first reference version: one query row at a time, scalar loops, a full row of scores.
void attention_rowwise(const float* q, const float* k, const float* v, float* o, const cpu::AttentionShape& a) {
  const float scale = 1.0f / std::sqrt(static_cast<float>(a.head_dim));
  const std::int64_t D = a.head_dim;
#pragma omp parallel
  {
    std::vector<float> score(static_cast<std::size_t>(a.lk)), acc(static_cast<std::size_t>(D));
#pragma omp for collapse(2)
    for (std::int64_t s = 0; s < a.seqs; ++s)
      for (std::int64_t h = 0; h < a.heads; ++h)
        for (std::int64_t i = 0; i < a.lq; ++i) {
          const float* qi = q + s * a.q_seq + i * a.q_row + h * D;
          const std::int64_t nk = a.mask == cpu::Mask::Causal ? std::min(a.lk, i + 1) : a.lk;
          float mx = -std::numeric_limits<float>::infinity();
          for (std::int64_t j = 0; j < nk; ++j) {
            const float* kj = k + s * a.k_seq + j * a.k_row + h * D;
            float dot = 0;
            for (std::int64_t d = 0; d < D; ++d) dot += qi[d] * kj[d];
            score[j] = dot * scale;
            mx = std::max(mx, score[j]);
          }
          float den = 0;
          for (std::int64_t j = 0; j < nk; ++j) den += (score[j] = std::exp(score[j] - mx));
          std::fill(acc.begin(), acc.end(), 0.f);
          for (std::int64_t j = 0; j < nk; ++j)
            for (std::int64_t d = 0; d < D; ++d) acc[d] += score[j] * v[s * a.v_seq + j * a.v_row + h * D + d];
          for (std::int64_t d = 0; d < D; ++d) o[s * a.o_seq + i * a.o_row + h * D + d] = acc[d] / den;
        }
  }
}

// args: case index, threads, implementation (0 tiled kernel, 1 row-wise reference)
void BM_Attention(benchmark::State& state) {
  const Case& c = kCases[state.range(0)];
  cpu::Context ctx(static_cast<int>(state.range(1)));
  Problem p(c);
  for (auto _ : state) {
    if (state.range(2) == 0) cpu::attention(ctx, p.q.data(), p.k.data(), p.v.data(), p.o.data(), p.a);
    else attention_rowwise(p.q.data(), p.k.data(), p.v.data(), p.o.data(), p.a);
    benchmark::ClobberMemory();
  }
  state.SetLabel(std::string(c.name) + (state.range(2) ? " rowwise-reference" : " tiled"));
  state.counters["GFLOPS"] = benchmark::Counter(p.flops * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["threads"] = ctx.threads();
}

// With --benchmark_repetitions=N, also report the best repetition (min time, max rate): on a
// machine shared with other jobs the best run is the one least disturbed.
void best_of(benchmark::internal::Benchmark* b) {
  b->ComputeStatistics("min", [](const std::vector<double>& v) { return *std::min_element(v.begin(), v.end()); });
  b->ComputeStatistics("max", [](const std::vector<double>& v) { return *std::max_element(v.begin(), v.end()); });
}

void attention_args(benchmark::internal::Benchmark* b) {
  b->ArgNames({"case", "thr", "ref"});
  const int all = std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  std::vector<int> thread_counts{1};
  if (all > 1) thread_counts.push_back(all);
  const auto ncases = static_cast<std::int64_t>(std::size(kCases));
  for (int t : thread_counts)
    for (std::int64_t i = 0; i < ncases; ++i) b->Args({i, t, 0});
  for (int t : thread_counts)
    for (std::int64_t i = 0; i < 2; ++i) b->Args({i, t, 1});  // the bench-mid cases, old kernel
  best_of(b);
  b->UseRealTime()->Unit(benchmark::kMillisecond)->MinTime(0.3);
}

}  // namespace

BENCHMARK(BM_Attention)->Apply(attention_args);
BENCHMARK_MAIN();
