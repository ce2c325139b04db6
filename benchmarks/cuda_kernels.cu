// Micro-benchmarks of the CUDA backend's kernels (plain CUDA events, no Google Benchmark, so
// the binary runs on a bare GPU machine): the measured ceilings (device copy bandwidth, bf16
// GEMM 8192³), cuBLASLt at the model's GEMM shapes with their epilogues, flash attention at
// the MST-spatial and VisDiT-joint sizes, and the fused norm/RoPE/residual kernels. Medians of
// event-timed repetitions after warm-up; GEMM inputs rotate over several buffer sets so that
// the 50-60 MB L2 cannot hold them. Random (never zero) data. Sections alone: --attention,
// --rows, --own-gemm, --mst-residual, --passes (the memory-bound kernels); --once runs each
// kernel once (for ncu).
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <string>
#include <vector>

#include "epona/cuda/gemm/gemm_batched.cuh"
#include "epona/cuda/ops.cuh"
#include "epona/cuda/runtime/side_stream.hpp"

using namespace epona;

namespace {

__global__ void fill_uniform_kernel(float* f, bf16* b, std::int64_t n, std::uint32_t seed, float lo, float hi) {
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < n;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    std::uint32_t h = static_cast<std::uint32_t>(i) * 2654435761u ^ seed * 2246822519u ^
                      static_cast<std::uint32_t>(i >> 32) * 3266489917u;
    h ^= h >> 15, h *= 2246822519u, h ^= h >> 13, h *= 3266489917u, h ^= h >> 16;
    const float v = lo + (hi - lo) * (h >> 8) * (1.0f / 16777216.0f);
    if (f) f[i] = v;
    if (b) b[i] = cuda::detail::from_f32<bf16>(v);
  }
}

template <class T>
Tensor<T, Cuda> random_device(cuda::Context& ctx, Shape shape, std::uint32_t seed, float lo = -1.f, float hi = 1.f) {
  Tensor<T, Cuda> t(std::move(shape));
  float* f = nullptr;
  bf16* b = nullptr;
  if constexpr (std::is_same_v<T, float>) f = t.data(); else b = t.data();
  fill_uniform_kernel<<<1024, 256, 0, ctx.stream()>>>(f, b, t.numel(), seed, lo, hi);
  EPONA_CUDA_CHECK_LAUNCH();
  return t;
}

bool g_once = false;  // --once: every kernel runs once (for profiling with ncu), timings meaningless

// Median milliseconds of `reps` event-timed calls after `warmup` untimed ones.
double median_ms(cuda::Context& ctx, int reps, const std::function<void(int)>& fn, int warmup = 3) {
  if (g_once) reps = 1, warmup = 0;
  for (int i = 0; i < warmup; ++i) fn(i);
  std::vector<cudaEvent_t> ev(2 * reps);
  for (auto& e : ev) EPONA_CUDA_CHECK(cudaEventCreate(&e));
  for (int i = 0; i < reps; ++i) {
    EPONA_CUDA_CHECK(cudaEventRecord(ev[2 * i], ctx.stream()));
    fn(i);
    EPONA_CUDA_CHECK(cudaEventRecord(ev[2 * i + 1], ctx.stream()));
  }
  ctx.synchronize();
  std::vector<double> ms(reps);
  for (int i = 0; i < reps; ++i) {
    float m = 0;
    EPONA_CUDA_CHECK(cudaEventElapsedTime(&m, ev[2 * i], ev[2 * i + 1]));
    ms[i] = m;
  }
  for (auto& e : ev) cudaEventDestroy(e);
  std::sort(ms.begin(), ms.end());
  return ms[reps / 2];
}

// Median milliseconds per call of `call` recorded kGraphCalls times into one CUDA graph.
constexpr int kGraphCalls = 20;
double median_graph_ms(cuda::Context& ctx, int reps, const std::function<void()>& call) {
  call();  // outside the capture: one-time setup (kernel attributes, buffers)
  cudaGraph_t graph = nullptr;
  cudaGraphExec_t exec = nullptr;
  EPONA_CUDA_CHECK(cudaStreamBeginCapture(ctx.stream(), cudaStreamCaptureModeRelaxed));
  try {
    for (int i = 0; i < kGraphCalls; ++i) call();
  } catch (...) {
    (void)cudaStreamEndCapture(ctx.stream(), &graph);
    if (graph) cudaGraphDestroy(graph);
    throw;
  }
  EPONA_CUDA_CHECK(cudaStreamEndCapture(ctx.stream(), &graph));
  EPONA_CUDA_CHECK(cudaGraphInstantiate(&exec, graph, 0));
  const double ms = median_ms(ctx, reps, [&](int) { EPONA_CUDA_CHECK(cudaGraphLaunch(exec, ctx.stream())); });
  cudaGraphExecDestroy(exec);
  cudaGraphDestroy(graph);
  return ms / kGraphCalls;
}

double g_gemm_ceiling = 0;  // TFLOP/s of the bf16 8192³ product, the reference for the rest

void row(const std::string& name, double ms, double flop, double bytes) {
  std::printf("%-58s %9.4f ms", name.c_str(), ms);
  if (flop > 0) {
    const double tf = flop / ms / 1e9;
    std::printf(" %8.1f TFLOP/s", tf);
    if (g_gemm_ceiling > 0) std::printf(" (%5.1f%% of ceiling)", 100.0 * tf / g_gemm_ceiling);
  }
  if (bytes > 0) std::printf(" %8.1f GB/s", bytes / ms / 1e6);
  std::printf("\n");
  std::fflush(stdout);
}

const char* epi_name(cuda::Epilogue e) {
  switch (e) {
    case cuda::Epilogue::None: return "bias";
    case cuda::Epilogue::GeluErf: return "bias+gelu_erf";
    case cuda::Epilogue::GeluTanh: return "bias+gelu_tanh";
    case cuda::Epilogue::Silu: return "bias+silu";
  }
  return "?";
}

// Operand sets of `items` products (x, w, bias and y each; items = 1: 2-d tensors) for use
// round robin: as many as make ~240 MB (so that the 50-60 MB L2 cannot hold them), at least
// `least`, at most 8. Without bias the bias tensors are empty.
template <class T>
struct OperandSets {
  std::vector<Tensor<T, Cuda>> x, w, bias, y;
  int count() const { return static_cast<int>(x.size()); }
};
template <class T>
OperandSets<T> operand_sets(cuda::Context& ctx, std::int64_t items, std::int64_t M, std::int64_t N, std::int64_t K,
                            bool bias, int least = 1) {
  const auto shape = [&](std::int64_t rows, std::int64_t cols) {
    return items == 1 ? Shape{rows, cols} : Shape{items, rows, cols};
  };
  const double bytes_per_set = double(items) * (M * K + N * K + M * N) * sizeof(T);
  const int sets = std::clamp(static_cast<int>(240e6 / bytes_per_set) + 1, least, 8);
  OperandSets<T> o;
  for (int s = 0; s < sets; ++s) {
    o.x.push_back(random_device<T>(ctx, shape(M, K), 10 * s + 1));
    o.w.push_back(random_device<T>(ctx, shape(N, K), 10 * s + 2, -0.03f, 0.03f));
    o.bias.push_back(bias ? random_device<T>(ctx, items == 1 ? Shape{N} : Shape{items, N}, 10 * s + 3)
                          : Tensor<T, Cuda>());
    o.y.push_back(Tensor<T, Cuda>(shape(M, N)));
  }
  return o;
}

// y = act(x wᵀ + b) over operand sets used round robin.
template <class T>
double bench_linear(cuda::Context& ctx, std::int64_t M, std::int64_t N, std::int64_t K, bool bias, cuda::Epilogue epi,
                    int reps, const char* label) {
  auto o = operand_sets<T>(ctx, 1, M, N, K, bias);
  const double ms = median_ms(ctx, reps, [&](int i) {
    const int s = i % o.count();
    cuda::linear(ctx, o.x[s], o.w[s], o.bias[s], o.y[s], epi);
  });
  char name[160];
  std::snprintf(name, sizeof name, "%s %s M=%lld N=%lld K=%lld %s", label,
                std::is_same_v<T, float> ? "f32" : "bf16", static_cast<long long>(M), static_cast<long long>(N),
                static_cast<long long>(K), bias ? epi_name(epi) : "");
  row(name, ms, 2.0 * M * N * K, 0);
  return ms;
}

std::string plan_name(const cuda::detail::TmaPlan& p) {
  return "planned " + std::to_string(p.rows) + " rows, " + std::to_string(p.splits) + " key ranges" +
         (p.splits > 1 ? (p.tail_only ? " (last row block)" : " (all row blocks)") : "") +
         (p.share_rows ? "" : ", unshared") + (p.narrow_last ? "" : ", wide last tile") +
         (p.ctas > 0 ? ", persistent over " + std::to_string(p.ctas) + " CTAs" : "");
}

// One attention shape timed with the automatic choice (first and last: its two medians show
// the run-to-run spread), Auto before the plans (EPONA_CUDA_ATTN_SPLIT=0) and after, every bf16
// kernel that can run it, and the planned TMA kernel under several plans.
void bench_attention_kernels(cuda::Context& ctx, const std::string& label, const bf16* q, const bf16* k,
                             const bf16* v, bf16* o, const cuda::AttentionShape& a, double flop, double bytes,
                             int reps) {
  using cuda::detail::FlashKernel;
  using cuda::detail::TmaPlan;
  const bool fits_short = a.lq <= 16 && a.lk <= 16;
  const auto params = cuda::detail::flash_params(q, k, v, o, a);
  const bool fits_wgmma = cuda::detail::wgmma_kernel_fits(ctx, params, cuda::detail::exact_head_dim(params));
  bool& split = ctx.policy().attention_split;
  const bool saved = split;
  // Eager (one launch after another: small kernels are bound by the host's launch cost) and
  // from a graph of kGraphCalls calls (as the samplers run them: kernel and dependency time).
  const auto time = [&](const std::string& name, FlashKernel kernel, const TmaPlan* plan) {
    try {
      const auto call = [&] { cuda::detail::attention(ctx, q, k, v, o, a, kernel, plan); };
      const double ms = median_ms(ctx, reps, [&](int) { call(); });
      row(label + " [" + name + "]", ms, flop, bytes);
      const double graph_ms = median_graph_ms(ctx, reps, call);
      row(label + " [" + name + "] in a graph", graph_ms, flop, bytes);
      return graph_ms;
    } catch (const epona::Error& e) {  // a TMA kernel refusing these strides, a plan too large
      std::printf("%-58s not run: %s\n", (label + " [" + name + "]").c_str(), e.what());
      return 0.0;
    }
  };
  double auto_ms[2] = {};
  for (const bool on : {false, true}) {
    split = on;
    const FlashKernel kernel = cuda::detail::auto_flash_kernel(ctx, q, k, v, o, a);
    std::string name = std::string(on ? "Auto, planned: " : "Auto, unplanned: ") + cuda::detail::flash_kernel_name(kernel);
    if (kernel == FlashKernel::TmaPlanned)
      name += ", " + plan_name(cuda::detail::auto_tma_plan(ctx, params, a.seqs, a.heads));
    auto_ms[on] = time(name, FlashKernel::Auto, nullptr);
  }
  if (auto_ms[0] > 0 && auto_ms[1] > 0)
    std::printf("  -> %s: Auto in a graph: unplanned %.1f us, planned %.1f us (x%.2f)\n", label.c_str(), 1e3 * auto_ms[0],
                1e3 * auto_ms[1], auto_ms[0] / auto_ms[1]);
  split = saved;
  for (const FlashKernel kernel : {FlashKernel::Rows64, FlashKernel::Rows128, FlashKernel::Rows64Split4,
                                   FlashKernel::Short, FlashKernel::Wgmma64, FlashKernel::Tma64,
                                   FlashKernel::Tma128, FlashKernel::Auto}) {
    if (kernel == FlashKernel::Short && !fits_short) continue;
    if (cuda::detail::is_wgmma(kernel) && !fits_wgmma) continue;
    time(cuda::detail::flash_kernel_name(kernel), kernel, nullptr);
  }
  if (!fits_wgmma || a.lk == 0 || fits_short) return;
  const TmaPlan plans[] = {{64, 1},       {64, 2},       {64, 3},          {64, 5},
                           {128, 1, true}, {128, 2, true}, {128, 3, true},  {128, 5, true},
                           {128, 2},       {128, 3},       {64, 1, false, true, false}, {128, 1, true, false, false},
                           {128, 1, true, true, true, ctx.info().multiprocessors},
                           {128, 1, true, false, true, ctx.info().multiprocessors}};
  for (const TmaPlan& plan : plans) time(plan_name(plan), FlashKernel::TmaPlanned, &plan);
}

// Self-attention over packed (seqs, L, 3, heads, 128) QKV into (seqs, L - q_first, heads,
// 128); q_first > 0: only the last L - q_first rows are queried (the DiTs' last single block).
template <class T>
void bench_attention(cuda::Context& ctx, std::int64_t seqs, std::int64_t heads, std::int64_t len, bool causal,
                     int reps, const char* label, std::int64_t q_first = 0) {
  const std::int64_t D = 128, c = heads * D, lq = len - q_first;
  auto qkv = random_device<T>(ctx, {seqs, len, 3 * c}, 77, -2.f, 2.f);
  Tensor<T, Cuda> out({seqs, lq, c});
  cuda::AttentionShape a;
  a.seqs = seqs, a.heads = heads, a.lq = lq, a.lk = len, a.head_dim = D;
  a.q_seq = a.k_seq = a.v_seq = len * 3 * c;
  a.q_row = a.k_row = a.v_row = 3 * c;
  a.o_seq = lq * c, a.o_row = c;
  a.mask = causal ? cuda::Mask::Causal : cuda::Mask::None;
  char name[160];
  std::snprintf(name, sizeof name, "attention %s %s %lld x %lld heads x %lld x %lld x 128%s", label,
                std::is_same_v<T, float> ? "f32" : "bf16", static_cast<long long>(seqs),
                static_cast<long long>(heads), static_cast<long long>(lq), static_cast<long long>(len),
                causal ? " causal" : "");
  // Full-square FLOP (compute-budget.md convention), also for causal.
  const double flop = 4.0 * seqs * heads * lq * len * D;
  const T* q = qkv.data() + q_first * 3 * c;
  if constexpr (std::is_same_v<T, bf16>) {
    bench_attention_kernels(ctx, name, q, qkv.data() + c, qkv.data() + 2 * c, out.data(), a, flop, 0, reps);
  } else {
    const double ms = median_ms(ctx, reps, [&](int) {
      cuda::attention(ctx, q, qkv.data() + c, qkv.data() + 2 * c, out.data(), a);
    });
    row(name, ms, flop, 0);
  }
}

// The MST's temporal attention as mst.hpp calls it: separate (frames, spatial, C) q, k, v
// and o, one causal sequence per spatial position over the frames; last_only: the last
// block's one query (the last frame) over all frames. Bytes: q, k, v read and o written once.
void bench_temporal(cuda::Context& ctx, bool last_only, int reps) {
  const std::int64_t frames = 10, spatial = 515, heads = 16, c = heads * 128, plane = frames * spatial * c;
  auto qkv = random_device<bf16>(ctx, {3, frames, spatial, c}, 78, -2.f, 2.f);
  Tensor<bf16, Cuda> out({frames, spatial, c});
  cuda::AttentionShape a;
  a.seqs = spatial, a.heads = heads, a.lq = a.lk = frames, a.head_dim = 128;
  a.q_seq = a.k_seq = a.v_seq = a.o_seq = c, a.q_row = a.k_row = a.v_row = a.o_row = spatial * c;
  a.mask = cuda::Mask::Causal;
  const bf16* q = qkv.data();
  if (last_only) {
    a.lq = 1, a.mask = cuda::Mask::None, a.q_row = a.o_row = 0;
    q += (frames - 1) * spatial * c;
  }
  const double bytes = 2.0 * (2 * plane + 2 * a.lq * spatial * c);
  char name[160];
  std::snprintf(name, sizeof name, "attention MST temporal bf16 515 x 16 heads x %lld x 10 x 128%s",
                static_cast<long long>(a.lq), last_only ? "" : " causal");
  const double flop = 4.0 * spatial * heads * a.lq * frames * 128;
  bench_attention_kernels(ctx, name, q, qkv.data() + plane, qkv.data() + 2 * plane, out.data(), a, flop, bytes, reps);

  // With the time layer's QK LayerNorm: the separate pass over q and k (in place on a copy,
  // as mst.hpp ran it before) then the attention, against the norm inside the attention
  // (attention_qk_layer_norm). Graph-timed; bytes: the attention's alone.
  auto qk = random_device<bf16>(ctx, {2, frames, spatial, c}, 80, -2.f, 2.f);
  auto params = random_device<float>(ctx, {4, c}, 81, 0.5f, 1.5f);
  bf16 *qn = qk.data() + (q - qkv.data()), *kn = qk.data() + plane;
  const float *w = params.data(), *b = params.data() + c;
  const std::int64_t rows_q = a.lq * spatial, rows_k = frames * spatial;
  const auto separate = [&] {  // as QkNormTransformerLayer::normalize_qk: one launch where it fits, else two
    if (!cuda::layer_norm_rope_qk(ctx, qn, rows_q, kn, rows_k, c, w, b, 1e-5f, w + 2 * c, b + 2 * c, 1e-5f, 128,
                                  nullptr, nullptr)) {
      cuda::layer_norm(ctx, qn, qn, rows_q, c, w, b, 1e-5f);
      cuda::layer_norm(ctx, kn, kn, rows_k, c, w + 2 * c, b + 2 * c, 1e-5f);
    }
    cuda::attention(ctx, qn, kn, qkv.data() + 2 * plane, out.data(), a);
  };
  const auto fused = [&] {
    cuda::attention_qk_layer_norm(ctx, q, qkv.data() + plane, qkv.data() + 2 * plane, out.data(), a, w, b, 1e-5f,
                                  w + 2 * c, b + 2 * c, 1e-5f);
  };
  cuda::detail::attention_qk_norm_forced() = true;  // timed also where Auto declines it (lq != lk)
  const double separate_ms = median_graph_ms(ctx, reps, separate), fused_ms = median_graph_ms(ctx, reps, fused);
  cuda::detail::attention_qk_norm_forced() = false;
  row(std::string(name) + " [QK LayerNorm pass + attention] in a graph", separate_ms, flop, bytes);
  row(std::string(name) + " [QK LayerNorm inside] in a graph", fused_ms, flop, bytes);
  std::printf("  -> QK LayerNorm inside the attention: %.1f -> %.1f us (x%.2f)\n", 1e3 * separate_ms, 1e3 * fused_ms,
              separate_ms / fused_ms);
}

// Products whose row count is a few past a multiple of 128 (the DiTs' 515 condition rows: 512
// image tokens + 3 pose tokens; 1027 joint rows): M rows as one product, M - tail rows alone,
// the tail alone, and the M - tail rows with the tail on a second stream (graph-timed, operand
// sets rotating). paired: the double blocks' batch-2 product (both items M rows; the tail is
// the first item's).
void bench_row_tail(cuda::Context& ctx, cuda::SideStream& side, std::int64_t M, std::int64_t N, std::int64_t K,
                    bool paired, cuda::Epilogue epi, const char* what, std::int64_t tail = 3) {
  const int items = paired ? 2 : 1;
  auto o = operand_sets<bf16>(ctx, items, M, N, K, true, 2);
  int call = 0;
  const auto product = [&](cuda::Context& c, int s, std::int64_t first, std::int64_t rows, int count) {
    const bf16 *x = o.x[s].data() + first * K, *w = o.w[s].data(), *b = o.bias[s].data();
    bf16* y = o.y[s].data() + first * N;
    cuda::linear_batched(c, x, K, w, b, y, N, rows, N, K, cuda::GemmBatch{count, M * K, N * K, N, M * N}, epi);
  };
  const auto timed = [&](const char* how, const std::function<void(int)>& fn) {
    const double ms = median_graph_ms(ctx, 15, [&] { fn(call++ % o.count()); });
    char name[200];
    std::snprintf(name, sizeof name, "%s %s M=%lld N=%lld K=%lld: %s", what, paired ? "pair" : "one",
                  static_cast<long long>(M), static_cast<long long>(N), static_cast<long long>(K), how);
    row(name, ms, 2.0 * items * M * N * K, 0);
    return ms;
  };
  const double full = timed("all rows", [&](int s) { product(ctx, s, 0, M, items); });
  const double body = timed("body rows only", [&](int s) { product(ctx, s, 0, M - tail, items); });
  const double tl = timed("tail rows only", [&](int s) { product(ctx, s, M - tail, tail, 1); });
  const double split = timed("body + tail on a side stream", [&](int s) {
    side.fork(ctx);
    product(side.side(ctx), s, M - tail, tail, 1);
    product(ctx, s, 0, M - tail, items);
    side.join(ctx);
  });
  std::printf("  -> all %.1f us, body %.1f, tail %.1f, body || tail %.1f (x%.2f)\n", 1e3 * full, 1e3 * body, 1e3 * tl,
              1e3 * split, full / split);
}

// The own Hopper GEMM (gemm_wgmma.cuh) against cuBLASLt at one shape, side by side: with the
// erf GELU through cuda::linear (switch on: fused; off: cuBLASLt + the table pass), and with
// no activation calling both directly.
void bench_own_gemm(cuda::Context& ctx, std::int64_t M, std::int64_t N, std::int64_t K, const char* what) {
  const bool saved = ctx.policy().own_gemm;
  for (const bool on : {false, true, false, true}) {
    ctx.policy().own_gemm = on;
    bench_linear<bf16>(ctx, M, N, K, false, cuda::Epilogue::GeluErf, 30,
                       (std::string(what) + (on ? " [own GEMM, GELU fused]" : " [cuBLASLt + GELU pass]")).c_str());
  }
  ctx.policy().own_gemm = saved;
  auto o = operand_sets<bf16>(ctx, 1, M, N, K, false);
  char name[200];
  std::snprintf(name, sizeof name, "%s bf16 M=%lld N=%lld K=%lld no act", what, static_cast<long long>(M),
                static_cast<long long>(N), static_cast<long long>(K));
  for (int round = 0; round < 2; ++round) {
    double ms = median_ms(ctx, 30, [&](int i) {
      const int s = i % o.count();
      cuda::linear(ctx, o.x[s].data(), K, o.w[s].data(), static_cast<const bf16*>(nullptr), o.y[s].data(), N, M, N, K);
    });
    row(std::string(name) + " [cuBLASLt]", ms, 2.0 * M * N * K, 0);
    ms = median_ms(ctx, 30, [&](int i) {
      const int s = i % o.count();
      cuda::detail::own_gemm(ctx, o.x[s].data(), K, o.w[s].data(), nullptr, o.y[s].data(), N, M, N, K,
                             cuda::detail::Identity{});
    });
    row(std::string(name) + " [own GEMM]", ms, 2.0 * M * N * K, 0);
  }
}

// The MST's residual updates, side by side: the branch product written in bf16 and added by
// the LayerNorm pass after it (add_layer_norm: float32 residual, bf16 normalised output), or
// added by the product itself into the float32 residual (linear_accumulate) and normalised by a
// plain LayerNorm pass; each step alone too. Then q, k, v as three products against one product
// of the stacked weights (N = 3C) at the MST's 5150 rows.
void bench_mst_residual(cuda::Context& ctx) {
  constexpr std::int64_t M = 5150, C = 2048;
  const auto ln_w = random_device<float>(ctx, {C}, 42, 0.5f, 1.5f), ln_b = random_device<float>(ctx, {C}, 43);
  Tensor<bf16, Cuda> normed({M, C});
  // The residual drifts over the timed calls (each adds a product); harmless for timing.
  auto x = random_device<float>(ctx, {M, C}, 41);
  const auto norm_only = [&] { cuda::layer_norm(ctx, x.data(), normed.data(), M, C, ln_w.data(), ln_b.data(), 1e-5f); };
  for (const std::int64_t K : {C, 4 * C}) {
    auto o = operand_sets<bf16>(ctx, 1, M, C, K, false);
    const std::string what = K == C ? "MST proj" : "MST c_proj";
    const auto product = [&](int s) { cuda::linear(ctx, o.x[s], o.w[s], Tensor<bf16, Cuda>(), o.y[s]); };
    const auto accumulate = [&](int s) {
      cuda::linear_accumulate(ctx, o.x[s].data(), K, o.w[s].data(), x.data(), C, M, C, K);
    };
    const auto add_norm = [&](int s) {
      cuda::add_layer_norm(ctx, x.data(), o.y[s].data(), normed.data(), M, C, ln_w.data(), ln_b.data(), 1e-5f);
    };
    const double flop = 2.0 * M * C * K;
    for (int round = 0; round < 2; ++round) {
      const auto timed = [&](const std::string& how, double f, const std::function<void(int)>& fn) {
        row(what + " " + how + (round ? " (2)" : ""), median_ms(ctx, 30, [&](int i) { fn(i % o.count()); }), f, 0);
      };
      timed("bf16 product + add_layer_norm", flop, [&](int s) { product(s), add_norm(s); });
      timed("linear_accumulate + layer_norm", flop, [&](int s) { accumulate(s), norm_only(); });
      timed("  bf16 product alone", flop, product);
      timed("  linear_accumulate alone", flop, accumulate);
      timed("  add_layer_norm alone", 0, add_norm);
      timed("  layer_norm alone", 0, [&](int) { norm_only(); });
    }
  }
  auto three = operand_sets<bf16>(ctx, 1, M, C, C, false, 3);
  auto stacked = operand_sets<bf16>(ctx, 1, M, 3 * C, C, false);
  for (int round = 0; round < 2; ++round) {
    row("MST q, k, v as three products", median_ms(ctx, 30, [&](int i) {
          for (int j = 0; j < 3; ++j) {
            const int s = (3 * i + j) % three.count();
            cuda::linear(ctx, three.x[0], three.w[s], Tensor<bf16, Cuda>(), three.y[s]);
          }
        }), 3 * 2.0 * M * C * C, 0);
    row("MST q, k, v as one stacked product (N = 3C)", median_ms(ctx, 30, [&](int i) {
          const int s = i % stacked.count();
          cuda::linear(ctx, stacked.x[s], stacked.w[s], Tensor<bf16, Cuda>(), stacked.y[s]);
        }), 3 * 2.0 * M * C * C, 0);
  }
}

}  // namespace

int main(int argc, char** argv) {
  const auto flag = [&](const char* name) { return std::find(argv + 1, argv + argc, std::string(name)) != argv + argc; };
  g_once = flag("--once");
  const bool attention_only = flag("--attention");  // only that section
  const bool rows_only = flag("--rows");            // only the row-tail experiment
  const bool own_only = flag("--own-gemm");         // only the own GEMM against cuBLASLt
  const bool residual_only = flag("--mst-residual");  // only the MST's residual paths and stacked q/k/v
  const bool passes_only = flag("--passes");          // only the memory-bound kernels
  if (!cuda::has_gpu()) {
    std::printf("no CUDA device: skipping\n");
    return 0;
  }
  try {
    cuda::Context ctx;
    const auto& d = ctx.info();
    std::printf("device: %s (sm_%d%d, %d SMs, %.1f GiB, L2 %.0f MiB)\n\n", d.name.c_str(), d.major, d.minor,
                d.multiprocessors, d.global_bytes / 1073741824.0, d.l2_bytes / 1048576.0);

    if (residual_only) {
      bench_mst_residual(ctx);
      ctx.synchronize();
      return 0;
    }
    if (own_only) {
      bench_own_gemm(ctx, 5150, 8192, 2048, "MST c_fc");
      bench_own_gemm(ctx, 5150, 2048, 8192, "MST c_proj");
      bench_own_gemm(ctx, 5150, 2048, 2048, "MST q/k/v/proj");
      bench_own_gemm(ctx, 1027, 6144, 2048, "VisDiT qkv");
      bench_own_gemm(ctx, 515, 3072, 1024, "TrajDiT qkv");
      bench_own_gemm(ctx, 8192, 8192, 8192, "square");
      ctx.synchronize();
      return 0;
    }
    if (rows_only) {
      cuda::SideStream side;
      using E = cuda::Epilogue;
      bench_row_tail(ctx, side, 515, 6144, 2048, true, E::None, "VisDiT double qkv");
      bench_row_tail(ctx, side, 515, 2048, 2048, true, E::None, "VisDiT double proj");
      bench_row_tail(ctx, side, 515, 8192, 2048, true, E::GeluTanh, "VisDiT double fc1");
      bench_row_tail(ctx, side, 515, 2048, 8192, true, E::None, "VisDiT double fc2");
      bench_row_tail(ctx, side, 1027, 6144, 2048, false, E::None, "VisDiT single q+kv");
      bench_row_tail(ctx, side, 1027, 8192, 2048, false, E::GeluTanh, "VisDiT single mlp");
      bench_row_tail(ctx, side, 1027, 2048, 10240, false, E::None, "VisDiT single linear2");
      bench_row_tail(ctx, side, 515, 3072, 1024, false, E::None, "TrajDiT cond qkv");
      bench_row_tail(ctx, side, 515, 4096, 1024, false, E::GeluTanh, "TrajDiT cond fc1");
      bench_row_tail(ctx, side, 515, 1024, 4096, false, E::None, "TrajDiT cond fc2");
      bench_row_tail(ctx, side, 515, 1024, 1024, false, E::None, "TrajDiT cond proj");
      bench_row_tail(ctx, side, 515, 2048, 1024, false, E::None, "TrajDiT single kv");
      bench_row_tail(ctx, side, 5150, 8192, 2048, false, E::None, "MST c_fc", 30);
      ctx.synchronize();
      return 0;
    }
    if (!attention_only && !passes_only) {  // the ceilings and the model GEMMs
      {  // Ceiling 1: device-to-device copy of 2 GiB, bytes read + written.
        const std::int64_t n = std::int64_t{1} << 29;
        auto a = random_device<float>(ctx, {n}, 1);
        Tensor<float, Cuda> b({n});
        const double ms = median_ms(ctx, 10, [&](int) { cuda::copy(ctx, b, a); });
        row("device copy 2 GiB (read + write)", ms, 0, 2.0 * n * 4);
      }
      // Ceiling 2: bf16 8192³.
      {
        const double ms = bench_linear<bf16>(ctx, 8192, 8192, 8192, false, cuda::Epilogue::None, 20, "ceiling");
        g_gemm_ceiling = 2.0 * 8192.0 * 8192.0 * 8192.0 / ms / 1e9;
        std::printf("  -> measured bf16 GEMM ceiling %.1f TFLOP/s\n", g_gemm_ceiling);
      }
      bench_linear<float>(ctx, 4096, 4096, 4096, false, cuda::Epilogue::None, 10, "fp32 (no TF32)");

      std::printf("\nmodel GEMM shapes (bf16, bias fused; the activation each layer uses)\n");
      struct Shape3 { std::int64_t M, N, K; cuda::Epilogue epi; const char* what; };
      const Shape3 shapes[] = {
          {5150, 2048, 2048, cuda::Epilogue::None, "MST q/k/v/proj"},
          {5150, 8192, 2048, cuda::Epilogue::GeluErf, "MST c_fc"},
          {5150, 8192, 2048, cuda::Epilogue::None, "MST c_fc (no act)"},
          {5150, 2048, 8192, cuda::Epilogue::None, "MST c_proj"},
          {1027, 6144, 2048, cuda::Epilogue::None, "VisDiT qkv"},
          {1027, 8192, 2048, cuda::Epilogue::GeluTanh, "VisDiT mlp.0"},
          {1027, 14336, 2048, cuda::Epilogue::None, "VisDiT single linear1"},
          {530, 3072, 1024, cuda::Epilogue::None, "TrajDiT qkv"},
          {530, 7168, 1024, cuda::Epilogue::None, "TrajDiT single linear1"},
      };
      for (const auto& s : shapes) bench_linear<bf16>(ctx, s.M, s.N, s.K, true, s.epi, 30, s.what);
    }

    if (!passes_only) {
      std::printf("\nflash attention (head dim 128, packed QKV)\n");
      bench_attention<bf16>(ctx, 10, 16, 515, false, 30, "MST spatial");
      bench_attention<bf16>(ctx, 1, 16, 515, false, 30, "MST spatial, last block");
      bench_attention<bf16>(ctx, 1, 16, 1027, false, 30, "VisDiT joint");
      bench_attention<bf16>(ctx, 1, 16, 1027, false, 30, "VisDiT last single", 515);
      // What the 3 rows past the last full 128-row block cost: the same keys, those rows not queried.
      bench_attention<bf16>(ctx, 1, 16, 1027, false, 30, "VisDiT joint, 1024 queries", 3);
      bench_attention<bf16>(ctx, 10, 16, 515, false, 30, "MST spatial, 512 queries", 3);
      bench_attention<bf16>(ctx, 1, 8, 530, false, 30, "TrajDiT joint");
      bench_attention<bf16>(ctx, 1, 8, 530, false, 30, "TrajDiT last single", 515);
      bench_attention<bf16>(ctx, 1, 16, 4096, false, 10, "long (fill check)");
      bench_attention<bf16>(ctx, 1, 16, 4096, true, 10, "long (fill check)");
      bench_attention<float>(ctx, 10, 16, 515, false, 5, "MST spatial");
      bench_temporal(ctx, false, 30);
      bench_temporal(ctx, true, 30);
    }
    if (attention_only) return 0;

    std::printf("\nmemory-bound kernels (bf16 activations; bytes = reads + writes)\n");
    {
      const std::int64_t rows = 5150, n = 2048;
      auto x = random_device<float>(ctx, {rows, n}, 5);  // the MST's float32 residual
      auto xb = random_device<bf16>(ctx, {rows, n}, 6);
      auto shift = random_device<bf16>(ctx, {n}, 7), scale = random_device<bf16>(ctx, {n}, 8);
      Tensor<bf16, Cuda> y({rows, n});
      double ms = median_ms(ctx, 30, [&](int) {
        cuda::layer_norm(ctx, x.data(), y.data(), rows, n, static_cast<const float*>(nullptr), nullptr, 1e-6f);
      });
      row("layer_norm f32->bf16 5150 x 2048", ms, 0, rows * n * (4.0 + 2.0));
      ms = median_ms(ctx, 30, [&](int) {
        cuda::layer_norm_modulate(ctx, xb.data(), y.data(), rows, n, shift.data(), scale.data(), 1e-6f);
      });
      row("layer_norm_modulate bf16 5150 x 2048", ms, 0, rows * n * 4.0);
      ms = median_ms(ctx, 30, [&](int) { cuda::add_gated(ctx, xb.data(), y.data(), shift.data(), rows, n); });
      row("add_gated bf16 5150 x 2048", ms, 0, rows * n * 6.0);
      ms = median_ms(ctx, 30, [&](int) { cuda::add_inplace(ctx, x.data(), y.data(), rows * n); });
      row("add_inplace f32 += bf16 5150 x 2048", ms, 0, rows * n * 10.0);
      ms = median_ms(ctx, 30, [&](int) { cuda::gelu_erf(ctx, xb.data(), rows * n); });
      row("gelu_erf bf16 5150 x 2048", ms, 0, rows * n * 4.0);
    }
    {
      // The MST's erf GELU after c_fc, out of place so that every call sees the same inputs
      // (in place, repeated GELUs would drift towards zero); EPONA_CUDA_TABLES=0: direct kernel.
      const std::int64_t rows = 5150, n = 8192;
      auto h = random_device<bf16>(ctx, {rows, n}, 13, -4.f, 4.f);
      Tensor<bf16, Cuda> y({rows, n});
      const double ms = median_ms(ctx, 30, [&](int) {
        cuda::detail::map_bf16(ctx, h.data(), y.data(), rows * n, cuda::detail::GeluErfOp{});
      });
      row("gelu_erf bf16 5150 x 8192 (MST c_fc output)", ms, 0, rows * n * 4.0);
      const double copy_ms = median_ms(ctx, 30, [&](int) { cuda::copy(ctx, y, h); });
      row("device copy of the same bytes (the pass's floor)", copy_ms, 0, rows * n * 4.0);
    }
    {
      const std::int64_t rows = 1027, heads = 16, D = 128, stride = 3 * heads * D;
      auto qkv = random_device<bf16>(ctx, {rows, stride}, 9);
      auto cs = random_device<float>(ctx, {rows, D / 2}, 10), sn = random_device<float>(ctx, {rows, D / 2}, 11);
      auto sc = random_device<float>(ctx, {D}, 12, 0.5f, 1.5f);
      double ms = median_ms(ctx, 30, [&](int) {
        cuda::rms_norm_heads(ctx, qkv.data(), rows, stride, heads, D, sc.data(), 1e-6f);
      });
      row("rms_norm_heads bf16 (q of 1027 x 16 x 128)", ms, 0, rows * heads * D * 4.0);
      ms = median_ms(ctx, 30, [&](int) {
        cuda::apply_rope(ctx, qkv.data(), rows, stride, heads, D, cs.data(), sn.data());
      });
      row("apply_rope bf16 (q of 1027 x 16 x 128)", ms, 0, rows * heads * D * 4.0 + rows * D * 4.0);
    }
    ctx.synchronize();
  } catch (const epona::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
  return 0;
}
