// The DiT step's small kernels old vs new in one process (plain CUDA events, no Google
// Benchmark): skinny-M products (at most 16 rows: the TrajDiT's trajectory stream, batch-1
// modulation vectors) in cuBLASLt vs the skinny kernel (skinny_linear.cuh, several rounds of
// loads in flight), and qk_norm_rope's head-per-warp vs row path (groups of 2, 4, 8 warp
// accesses) at the VisDiT's and TrajDiT's sizes; the MST's QK LayerNorm + RoPE pass. Each row times a recorded graph of calls, each on its own copy of the weights (or qkv
// buffer), at least 20 and 256 MB in all, so that the 50-60 MB L2 holds none of them (the
// sampler's weights are cold too), and reports the median per call. --profile runs each variant once, eagerly,
// inside cudaProfilerStart/Stop (for ncu; the order is printed). The DiTs' condition-stream
// products (515-1027 rows) in cuBLASLt vs the few-rows GEMM (gemm_few_rows.cuh): its own
// choice of tile through linear, with and without programmatic launches, and each tile.
// Usage: bench_cuda_small_kernels [--repeats N] [--profile] [--only skinny|few_rows|qk]
#include <cuda_profiler_api.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <functional>
#include <string>
#include <vector>

#include "epona/cuda/ops.cuh"
#include "epona/cuda/attention/qk_layer_norm_rope.cuh"
#include "epona/cuda/attention/qk_rms_norm_rope.cuh"
#include "gpu_event_timer.cuh"

using namespace epona;

namespace {

constexpr std::int64_t kPoolBytes = std::int64_t{256} << 20;  // > 4x the L2

// Calls (one buffer copy each) per recorded graph for buffers of `bytes`.
int calls_for(std::int64_t bytes) {
  return static_cast<int>(std::clamp<std::int64_t>((kPoolBytes + bytes - 1) / bytes, 20, 256));
}

__global__ void fill_kernel(float* f, bf16* b, std::int64_t n, std::uint32_t seed) {
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < n;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    std::uint32_t h = static_cast<std::uint32_t>(i) * 2654435761u ^ seed * 2246822519u;
    h ^= h >> 15, h *= 2246822519u, h ^= h >> 13, h *= 3266489917u, h ^= h >> 16;
    const float v = (h >> 8) * (2.0f / 16777216.0f) - 1.0f;  // [-1, 1): never all zeros
    if (f) f[i] = v;
    if (b) b[i] = cuda::detail::from_f32<bf16>(v);
  }
}
template <class T>
Tensor<T, Cuda> random_device(cuda::Context& ctx, std::int64_t n, std::uint32_t seed) {
  Tensor<T, Cuda> t({n});
  if constexpr (std::is_same_v<T, float>)
    fill_kernel<<<1024, 256, 0, ctx.stream()>>>(t.data(), nullptr, n, seed);
  else
    fill_kernel<<<1024, 256, 0, ctx.stream()>>>(nullptr, t.data(), n, seed);
  EPONA_CUDA_CHECK_LAUNCH();
  return t;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

struct Options {
  int repeats = 30;
  bool profile = false;
  std::string only;  // one section (skinny, few_rows, qk) or all
  bool runs(const char* section) const { return only.empty() || only == section; }
};

// Times fn(i) for i = 0..calls-1 recorded as one graph (after an eager warm-up call of each i);
// returns the median microseconds per call.
double graph_us(cuda::Context& ctx, int repeats, int calls, const std::function<void(int)>& fn) {
  for (int i = 0; i < calls; ++i) fn(i);
  ctx.synchronize();
  cudaGraph_t graph;
  cudaGraphExec_t exec;
  EPONA_CUDA_CHECK(cudaStreamBeginCapture(ctx.stream(), cudaStreamCaptureModeThreadLocal));
  for (int i = 0; i < calls; ++i) fn(i);
  EPONA_CUDA_CHECK(cudaStreamEndCapture(ctx.stream(), &graph));
  EPONA_CUDA_CHECK(cudaGraphInstantiate(&exec, graph, 0));
  const auto runs = bench::event_times_ms(ctx, repeats, 3, [&] { EPONA_CUDA_CHECK(cudaGraphLaunch(exec, ctx.stream())); });
  EPONA_CUDA_CHECK(cudaGraphExecDestroy(exec));
  EPONA_CUDA_CHECK(cudaGraphDestroy(graph));
  return 1e3 * median(runs) / calls;
}

// One eager call inside the profiler range, named on stdout (ncu lists kernels in this order).
void profiled(const Options& o, cuda::Context& ctx, const std::string& what, const std::function<void()>& fn) {
  if (!o.profile) return;
  ctx.synchronize();
  EPONA_CUDA_CHECK(cudaProfilerStart());
  fn();
  ctx.synchronize();
  EPONA_CUDA_CHECK(cudaProfilerStop());
  std::printf("# profiled: %s\n", what.c_str());
}

void report(const std::string& name, double us, double bytes) {
  std::printf("{\"name\": \"%s\", \"us\": %.3f, \"gbps\": %.0f}\n", name.c_str(), us, bytes / (us * 1e3));
  std::fflush(stdout);
}

using Variants = std::vector<std::pair<std::string, std::function<void(int)>>>;

// Each variant timed as `calls` recorded calls and reported as tag_name with its speed-up over
// the first variant (`first_label`) and the bandwidth of `bytes` per call.
void time_variants(const Options& o, cuda::Context& ctx, const std::string& tag, int calls, double bytes,
                   const Variants& variants, const char* first_label) {
  double base = 0;
  for (const auto& [name, fn] : variants) {
    const double us = graph_us(ctx, o.repeats, calls, fn);
    if (base == 0) base = us;
    report(tag + "_" + name, us, bytes);
    std::printf("# %s %s: %.2f us (%.2fx %s), %.0f GB/s\n", tag.c_str(), name.c_str(), us, base / us, first_label,
                bytes / (us * 1e3));
    profiled(o, ctx, tag + "_" + name, [&] { fn(0); });
  }
}

// The skinny kernel called directly with `Unroll` chunks per round of loads.
template <int Unroll, class T>
std::function<void(int)> skinny_with(cuda::Context& ctx, std::function<cuda::detail::LinearArgs<T>(int)> args,
                                     Epilogue epi) {
  return [&ctx, args, epi](int i) {
    const bool ran = cuda::detail::skinny_linear<T, Unroll>(ctx, args(i), epi);
    EPONA_CHECK(ran, "skinny kernel declined");
  };
}

struct ProductShape {
  const char* name;
  std::int64_t M, N, K;
  bool gelu;
};

// A product's operands: one weight copy per recorded call (cold weights, see calls_for), x,
// bias and y; the product's epilogue.
template <class T>
struct ProductOperands {
  std::int64_t wn;
  int calls;
  Tensor<T, Cuda> pool, x, bias, y;
  Epilogue epi;
  ProductOperands(cuda::Context& ctx, const ProductShape& s, std::uint32_t seed)
      : wn(s.N * s.K),
        calls(calls_for(wn * std::int64_t{sizeof(T)})),
        pool(random_device<T>(ctx, wn * calls, seed)),
        x(random_device<T>(ctx, s.M * s.K, seed + 1)),
        bias(random_device<T>(ctx, s.N, seed + 2)),
        y({s.M, s.N}),
        epi(s.gelu ? Epilogue::GeluTanh : Epilogue::None) {}
  const T* w(int i) const { return pool.data() + i * wn; }
};

// cuBLASLt vs the skinny kernel (default rounds of 2 chunks, and 1, 4) on one product shape.
template <class T>
void time_product(const Options& o, cuda::Context& ctx, const ProductShape& s) {
  ProductOperands<T> p(ctx, s, 1);
  const auto epi = p.epi;
  const auto args = [&](int i) {
    return cuda::detail::LinearArgs<T>{p.x.data(), s.K, p.w(i), p.bias.data(), p.y.data(), s.N,
                                       static_cast<int>(s.M), static_cast<int>(s.N), static_cast<int>(s.K)};
  };
  const auto via_linear = [&](bool skinny) {
    return [&, skinny](int i) {
      ctx.policy().skinny_linear = skinny;
      const auto a = args(i);
      cuda::linear(ctx, a.x, a.ldx, a.w, a.bias, a.y, a.ldy, s.M, s.N, s.K, epi);
    };
  };
  const std::string tag = std::string("linear_") + (std::is_same_v<T, float> ? "f32_" : "bf16_") + s.name;
  const double bytes = double(sizeof(T)) * (p.wn + s.M * s.K + s.M * s.N);
  Variants variants{{"cublaslt", via_linear(false)}, {"skinny", via_linear(true)}};
  if constexpr (!std::is_same_v<T, float>)
    variants.insert(variants.end(), {{"skinny_u1", skinny_with<1, T>(ctx, args, epi)},
                                     {"skinny_u4", skinny_with<4, T>(ctx, args, epi)}});
  time_variants(o, ctx, tag, p.calls, bytes, variants, "cuBLASLt");
  ctx.policy().skinny_linear = true;
}

// A product of the DiTs' condition streams in cuBLASLt, the few-rows GEMM through linear (its
// choice of tile; with and without programmatic launches), with all of w loaded after the wait,
// and each of its tiles called directly.
void time_few_rows(const Options& o, cuda::Context& ctx, const ProductShape& s) {
  ProductOperands<bf16> p(ctx, s, 13);
  const auto via_linear = [&](bool few_rows, bool pdl) {
    return [&, few_rows, pdl](int i) {
      const cuda::KernelPolicy was = ctx.policy();
      ctx.policy().few_rows_gemm = few_rows;
      ctx.policy().programmatic_launch = pdl;
      cuda::linear(ctx, p.x.data(), s.K, p.w(i), p.bias.data(), p.y.data(), s.N, s.M, s.N, s.K, p.epi);
      ctx.policy() = was;
    };
  };
  Variants variants{{"cublaslt", via_linear(false, true)},
                    {"few_rows", via_linear(true, true)},
                    {"few_rows_no_pdl", via_linear(true, false)}};
  const auto direct = [&](int choice, bool early_weights) {
    return [&, choice, early_weights](int i) {
      const bool ran = cuda::detail::few_rows_gemm(ctx, p.x.data(), s.K, p.w(i), p.bias.data(), p.y.data(), s.N,
                                                   s.M, s.N, s.K, p.epi, choice, early_weights);
      EPONA_CHECK(ran, "few-rows GEMM declined tile ", choice);
    };
  };
  variants.emplace_back("few_rows_late_weights", direct(-1, false));  // what loading w before the wait is worth
  for (int choice = 0; choice < cuda::detail::fr::kChoices; ++choice)
    variants.emplace_back("tile" + std::to_string(choice), direct(choice, true));
  std::printf("# %s: the model picks tile %d\n", s.name,
              static_cast<int>(cuda::detail::fr::choose(s.M, s.N, s.K, ctx.info().multiprocessors)));
  time_variants(o, ctx, std::string("few_rows_") + s.name, p.calls, double(sizeof(bf16)) * (p.wn + s.M * (s.K + s.N)),
                variants, "cuBLASLt");
}

// qk_norm_rope head-per-warp vs row path over the segments of one DiT's joint qkv rows.
template <class T, std::size_t S>
void time_qk(const Options& o, cuda::Context& ctx, const char* name, std::int64_t rows, std::int64_t heads,
             const std::array<std::array<std::int64_t, 3>, S>& ranges) {
  struct Segment {
    std::int64_t first, q_first, end;
    const float* q_scale;
    const float* k_scale;
  };
  const std::int64_t width = heads * 128, stride = 3 * width, n = rows * stride;
  const int calls = calls_for(n * std::int64_t{sizeof(T)});
  auto pool = random_device<T>(ctx, n * calls, 4);
  const auto cos = random_device<float>(ctx, rows * 64, 5), sin = random_device<float>(ctx, rows * 64, 6);
  const auto scale = random_device<float>(ctx, 128, 7);
  std::array<Segment, S> segs{};
  double moved = 0;
  for (std::size_t i = 0; i < S; ++i) {
    segs[i] = {ranges[i][0], ranges[i][1], ranges[i][2], scale.data(), scale.data()};
    moved += 2.0 * double(sizeof(T)) * width * double((ranges[i][2] - ranges[i][0]) + (ranges[i][2] - ranges[i][1]));
  }
  const std::string tag = std::string("qk_norm_rope_") + (std::is_same_v<T, float> ? "f32_" : "bf16_") + name;
  const int default_accesses = cuda::detail::qk_rows_accesses();
  Variants variants;
  for (const int accesses : {0, 2, 4, 8})  // 0: the head-per-warp kernel
    variants.emplace_back(accesses ? "rows_a" + std::to_string(accesses) : "heads", [&, accesses](int i) {
      ctx.policy().qk_norm_rope_rows = accesses > 0;
      cuda::detail::qk_rows_forced() = accesses > 0;  // timed where it does not pay too
      cuda::detail::qk_rows_accesses() = accesses > 0 ? accesses : default_accesses;
      cuda::qk_norm_rope(ctx, pool.data() + i * n, stride, width, heads, 128, 1e-6f, cos.data(), sin.data(),
                         segs);
    });
  time_variants(o, ctx, tag, calls, moved, variants, "head-per-warp");
  ctx.policy().qk_norm_rope_rows = true;
  cuda::detail::qk_rows_forced() = false;
  cuda::detail::qk_rows_accesses() = default_accesses;
}

// The MST's QK LayerNorm (+ RoPE in the space layers) over q and k of ten frames (5150 x 2048
// each): the fused kernel with the rotation, the same without it (the time layers: the norm's
// pass alone, what the rotation should cost nothing over), and the unfused ops (two
// layer_norm, two apply_rope launches).
void time_mst_qk(const Options& o, cuda::Context& ctx) {
  constexpr std::int64_t rows = 5150, n = 2048, heads = 16, head_dim = n / heads, per = rows * n;
  const int calls = calls_for(2 * per * std::int64_t{sizeof(bf16)});
  auto pool = random_device<bf16>(ctx, 2 * per * calls, 8);
  const auto cos = random_device<float>(ctx, rows * head_dim / 2, 9), sin = random_device<float>(ctx, rows * head_dim / 2, 10);
  const auto weight = random_device<float>(ctx, n, 11), bias = random_device<float>(ctx, n, 12);
  const auto fused = [&](bool rope) {
    return [&, rope](int i) {
      bf16* q = pool.data() + 2 * i * per;
      const bool ran = cuda::layer_norm_rope_qk(ctx, q, rows, q + per, rows, n, weight.data(), bias.data(), 1e-5f,
                                                weight.data(), bias.data(), 1e-5f, head_dim,
                                                rope ? cos.data() : nullptr, rope ? sin.data() : nullptr);
      EPONA_CHECK(ran, "layer_norm_rope_qk declined the MST's rows");
    };
  };
  const auto unfused = [&](int i) {
    bf16* q = pool.data() + 2 * i * per;
    for (bf16* x : {q, q + per}) {
      cuda::layer_norm(ctx, x, x, rows, n, weight.data(), bias.data(), 1e-5f);
      cuda::apply_rope(ctx, x, rows, n, heads, head_dim, cos.data(), sin.data());
    }
  };
  const double moved = 4.0 * double(sizeof(bf16)) * per;  // q and k read and written once
  time_variants(o, ctx, "mst_qk_layer_norm", calls, moved,
                {{"fused_rope", fused(true)}, {"fused_norm_only", fused(false)}, {"unfused_rope", unfused}},
                "fused_rope");
}

}  // namespace

int main(int argc, char** argv) {
  try {
    Options o;
    for (int i = 1; i < argc; ++i) {
      if (!std::strcmp(argv[i], "--profile")) o.profile = true;
      else if (!std::strcmp(argv[i], "--repeats") && i + 1 < argc) o.repeats = std::atoi(argv[++i]);
      else if (!std::strcmp(argv[i], "--only") && i + 1 < argc) o.only = argv[++i];
      else fail("unknown option ", argv[i], " (--repeats N, --profile, --only skinny|few_rows|qk)");
    }
    EPONA_CHECK(o.only.empty() || o.only == "skinny" || o.only == "few_rows" || o.only == "qk", "--only ", o.only,
                ": not a section (skinny, few_rows, qk)");
    if (!cuda::has_gpu()) {
      std::printf("no CUDA device: nothing to measure\n");
      return 0;
    }
    cuda::Context ctx;
    std::printf("# device: %s, %d SMs\n", ctx.info().name.c_str(), ctx.info().multiprocessors);
    // The TrajDiT's trajectory stream (15 rows, D 1024, MLP 4096), batch-1 modulation vectors.
    const std::vector<ProductShape> shapes{{"traj_qkv", 15, 3072, 1024, false},   {"traj_proj", 15, 1024, 1024, false},
                                    {"traj_fc1", 15, 4096, 1024, true},    {"traj_fc2", 15, 1024, 4096, false},
                                    {"traj_linear2", 15, 1024, 5120, false}, {"traj_mod", 1, 6144, 1024, false},
                                    {"vis_mod", 1, 12288, 2048, false}};
    if (o.runs("skinny")) {
      for (const auto& s : shapes) time_product<bf16>(o, ctx, s);
      for (const auto& s : {shapes[0], shapes[4]}) time_product<float>(o, ctx, s);
    }
    if (o.runs("few_rows")) {
      // The condition streams: TrajDiT (D 1024; 515 rows, 530 in the single blocks), VisDiT (D
      // 2048; 515 rows in the double blocks, 1027 in the single blocks).
      const std::vector<ProductShape> cond{
          {"traj_qkv", 515, 3072, 1024, false}, {"traj_proj", 515, 1024, 1024, false},
          {"traj_fc1", 515, 4096, 1024, true},  {"traj_fc2", 515, 1024, 4096, false},
          {"traj_kv", 530, 2048, 1024, false},  {"vis_qkv", 515, 6144, 2048, false},
          {"vis_fc1", 515, 8192, 2048, true},   {"vis_fc2", 515, 2048, 8192, false},
          {"vis_single_linear1", 1027, 14336, 2048, false}};
      for (const auto& s : cond) time_few_rows(o, ctx, s);
    }
    if (o.runs("qk")) {
      using R = std::array<std::int64_t, 3>;
      time_qk<bf16, 2>(o, ctx, "vis", 1027, 16, std::array<R, 2>{R{0, 0, 515}, R{515, 515, 1027}});
      time_qk<bf16, 2>(o, ctx, "traj", 530, 8, std::array<R, 2>{R{0, 0, 515}, R{515, 515, 530}});
      time_qk<bf16, 1>(o, ctx, "traj_pruned", 530, 8, std::array<R, 1>{R{0, 515, 530}});
      time_qk<float, 2>(o, ctx, "vis", 1027, 16, std::array<R, 2>{R{0, 0, 515}, R{515, 515, 1027}});
      time_mst_qk(o, ctx);
    }
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_cuda_small_kernels: %s\n", e.what());
    return 1;
  }
}
