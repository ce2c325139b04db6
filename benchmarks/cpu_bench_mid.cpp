// The CPU side of the side-by-side comparison with PyTorch (pytorch-baseline.md, "bench-mid"):
// MST evaluate (10 frames), one TrajDiT and one VisDiT evaluation, DC-AE decode of a 128x256
// image, with float32 and bf16 weights, at the thread counts asked for. Random weights.
// Prints one JSON object per line, like benchmarks/pytorch/official_bench.py, so that
// benchmarks/cpu_side_by_side.sh can pair the two: medians of wall time, the process's and
// the main thread's CPU time (for shared machines, where the wall clock lies), GFLOP/s from
// the official FLOP count (compute-budget.md), and which kernels ran (isa, tile).
//
//   bench_cpu_bench_mid [--threads 2,all] [--weights f32,bf16] [--calls mst,traj_eval,vis_eval,dcae_decode,gemm2048]
//                       [--repeats 7] [--warmup 2] [--dcae-size 128x256]
// --calls gemm_shapes (not in the default set): the model's GEMM shapes and the DC-AE's largest
// convolution alone. EPONA_CPU_ISA / EPONA_CPU_TILE select kernels (cpu_features.hpp, gemm.hpp);
// EPONA_CPU_CONV=direct runs 3x3 convolutions as im2col GEMMs instead of Winograd (conv.hpp).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <fstream>
#include <functional>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench_stats.hpp"
#include "bench_mid_world.hpp"
#include "epona/core/arena.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/cpu/cpu_features.hpp"
#include "epona/cpu/gemm.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/world_model.hpp"

using namespace epona;

namespace {

// ---- options --------------------------------------------------------------------------

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream in(s);
  for (std::string item; std::getline(in, item, ',');)
    if (!item.empty()) out.push_back(item);
  return out;
}

int hardware_threads() { return std::max(1, static_cast<int>(std::thread::hardware_concurrency())); }

struct Options {
  std::vector<int> threads{2, hardware_threads()};
  std::vector<std::string> weights{"f32", "bf16"};
  std::vector<std::string> calls{"mst", "traj_eval", "vis_eval", "dcae_decode", "gemm2048"};
  int repeats = 7, warmup = 2;
  std::int64_t dcae_h = 128, dcae_w = 256;

  bool wants(const std::string& call) const { return std::find(calls.begin(), calls.end(), call) != calls.end(); }
};

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    EPONA_CHECK(i + 1 < argc, "option ", a, " needs a value (see the header of cpu_bench_mid.cpp)");
    const std::string v = argv[++i];
    if (a == "--threads") {
      o.threads.clear();
      for (const auto& t : split(v)) o.threads.push_back(t == "all" ? hardware_threads() : std::stoi(t));
    } else if (a == "--weights") {
      o.weights = split(v);
      for (const auto& w : o.weights) EPONA_CHECK(w == "f32" || w == "bf16", "--weights: f32 or bf16, got ", w);
    } else if (a == "--calls") {
      o.calls = split(v);
    } else if (a == "--repeats") {
      o.repeats = std::max(1, std::stoi(v));
    } else if (a == "--warmup") {
      o.warmup = std::max(0, std::stoi(v));
    } else if (a == "--dcae-size") {
      EPONA_CHECK(std::sscanf(v.c_str(), "%ldx%ld", &o.dcae_h, &o.dcae_w) == 2, "--dcae-size: HxW, got ", v);
    } else {
      fail("unknown option ", a, " (see the header of cpu_bench_mid.cpp)");
    }
  }
  return o;
}

// ---- timing ---------------------------------------------------------------------------

double seconds(clockid_t clock) {
  timespec t{};
  clock_gettime(clock, &t);
  return double(t.tv_sec) + 1e-9 * double(t.tv_nsec);
}

struct Runs {
  std::vector<double> wall_ms, process_cpu_ms, thread_cpu_ms;
};

Runs measure(const std::function<void()>& fn, int repeats, int warmup) {
  for (int i = 0; i < warmup; ++i) fn();
  Runs r;
  for (int i = 0; i < repeats; ++i) {
    const double w0 = seconds(CLOCK_MONOTONIC), p0 = seconds(CLOCK_PROCESS_CPUTIME_ID), t0 = seconds(CLOCK_THREAD_CPUTIME_ID);
    fn();
    r.thread_cpu_ms.push_back(1e3 * (seconds(CLOCK_THREAD_CPUTIME_ID) - t0));
    r.process_cpu_ms.push_back(1e3 * (seconds(CLOCK_PROCESS_CPUTIME_ID) - p0));
    r.wall_ms.push_back(1e3 * (seconds(CLOCK_MONOTONIC) - w0));
  }
  return r;
}

using bench::median;
double minimum(const std::vector<double>& v) { return *std::min_element(v.begin(), v.end()); }

std::string json_list(const std::vector<double>& v) {
  std::ostringstream s;
  s << '[';
  for (std::size_t i = 0; i < v.size(); ++i) s << (i ? ", " : "") << v[i];
  return s.str() + ']';
}

// The GEMM tile of the kernels that ran: AMX's for bf16 weights under it, the AVX-512 one when
// an AVX-512 family runs (float32 weights under AMX too), else "-".
const char* tile_name(bool bf16_weights = false) {
  const cpu::Isa isa = cpu::active_isa();
  if (isa == cpu::Isa::Amx && bf16_weights) return "amx32x32";
  if (isa != cpu::Isa::Avx512 && isa != cpu::Isa::Avx512Bf16 && isa != cpu::Isa::Amx) return "-";
  return cpu::detail::avx512_tile() == cpu::gemm::Tile::Wide ? "6x64" : "14x32";
}

void emit(const std::string& name, const std::string& weights, int threads, double gflop, const Runs& r) {
  const double ms = median(r.wall_ms);
  std::printf(
      "{\"name\": \"%s\", \"weights\": \"%s\", \"threads\": %d, \"ms\": %.4f, \"min_ms\": %.4f, \"gflop\": %.4f, "
      "\"gflops\": %.1f, \"process_cpu_ms\": %.4f, \"thread_cpu_ms\": %.4f, \"isa\": \"%s\", \"tile\": \"%s\", "
      "\"runs\": %s}\n",
      name.c_str(), weights.c_str(), threads, ms, minimum(r.wall_ms), gflop, gflop / (ms * 1e-3),
      median(r.process_cpu_ms), median(r.thread_cpu_ms), cpu::isa_name(cpu::active_isa()), tile_name(weights == "bf16"),
      json_list(r.wall_ms).c_str());
  std::fflush(stdout);
}

std::string cpu_model_name() {
  std::ifstream in("/proc/cpuinfo");
  for (std::string line; std::getline(in, line);)
    if (line.rfind("model name", 0) == 0) return line.substr(line.find(':') + 2);
  return "unknown";
}

// ---- the bench-mid models -------------------------------------------------------------

using bench::randn;

// The world model with its inputs, the MST outputs the DiTs condition on, and arenas.
template <class W>
struct World : bench::BenchMidWorld<W> {
  // One DiT evaluation (cond_in included, as the official forward) as a callable.
  std::function<void()> dit_call(bool vis, double& gflop) {
    auto& self = *this;  // the base's members by name
    const auto& dit = vis ? self.wm.vis_dit() : self.wm.traj_dit();
    const auto& x_ids = vis ? self.ids.img : self.ids.traj;
    const nn::JointRows rows{self.cfg.tokens_per_frame(), x_ids.size(1)};
    gflop = dit.forward_flops(rows, false).total() / 1e9;
    auto x = std::make_shared<Tensor<float, Cpu>>(self.dit_input(vis));
    auto v = std::make_shared<Tensor<float, Cpu>>(x->shape());
    auto t = std::make_shared<Tensor<float, Cpu>>(Tensor<float, Cpu>::full({1}, 0.37f));
    auto arena = std::make_shared<Arena<Cpu>>(dit.forward_bytes(1, rows));
    return [&self, &dit, &x_ids, x, v, t, arena] {
      dit.forward(self.wm.context(), *arena, *x, x_ids, self.stt, self.ids.cond, *t, self.pose_emb, *v);
    };
  }
};

template <class W>
void bench_world(const Options& o, const std::string& weights) {
  auto world = std::make_unique<World<W>>();
  world->evaluate_mst();  // the DiTs condition on its outputs
  for (int threads : o.threads) {
    world->wm.context().set_threads(threads);
    if (o.wants("mst"))
      emit("mst", weights, threads, world->wm.mst().evaluate_flops(false).total() / 1e9,
           measure([&] { world->evaluate_mst(); }, o.repeats, o.warmup));
    for (const auto& [name, vis] : {std::pair<const char*, bool>{"traj_eval", false}, {"vis_eval", true}}) {
      if (!o.wants(name)) continue;
      double gflop = 0;
      const auto call = world->dit_call(vis, gflop);
      emit(name, weights, threads, gflop, measure(call, o.repeats, o.warmup));
    }
  }
}

template <class W>
void bench_dcae(const Options& o, const std::string& weights) {
  auto ae = std::make_unique<Dcae<Cpu, W>>(DcaeConfig{});
  ae->randomize(1);
  const auto z = randn({1, 32, o.dcae_h / 32, o.dcae_w / 32}, 5);
  const double gflop = dcae_flops(ae->config(), o.dcae_h, o.dcae_w, 1).decode_total() / 1e9;
  for (int threads : o.threads) {
    cpu::Context ctx(threads);
    emit("dcae_decode", weights, threads, gflop, measure([&] { (void)ae->decode(ctx, z, false); }, o.repeats, o.warmup));
  }
}

// The float32 GEMM ceiling of pytorch-baseline.md: 2048³ through linear (no bias).
void bench_gemm(const Options& o) {
  constexpr std::int64_t n = 2048;
  const auto a = randn({n, n}, 6), b = randn({n, n}, 7);
  Tensor<float, Cpu> c({n, n});
  for (int threads : o.threads) {
    cpu::Context ctx(threads);
    emit("gemm2048", "f32", threads, 2.0 * n * n * n / 1e9,
         measure([&] { cpu::linear<float>(ctx, a.data(), n, b.data(), nullptr, c.data(), n, n, n, n); }, o.repeats,
                 o.warmup));
  }
}

// The model's GEMM shapes one by one (y = x·Wᵀ, fp32 and bf16 weights) and the DC-AE's hottest
// convolution: the kernels' own speed next to the whole calls.
void bench_gemm_shapes(const Options& o) {
  struct Shape3 {
    const char* what;
    std::int64_t M, N, K;
  };
  const Shape3 shapes[] = {{"mst_qkv", 1310, 1024, 1024},      {"mst_mlp_up", 1310, 4096, 1024},
                           {"mst_mlp_down", 1310, 1024, 4096}, {"vis_img_qkv", 128, 3072, 1024},
                           {"vis_single_in", 259, 7168, 1024}, {"vis_single_out", 259, 1024, 5120},
                           {"traj_qkv", 15, 1536, 512},        {"traj_cond_mlp", 131, 2048, 512}};
  for (int threads : o.threads) {
    cpu::Context ctx(threads);
    for (const auto& s : shapes) {
      const auto x = randn({s.M, s.K}, 8), wf = randn({s.N, s.K}, 9, 0.03f);
      Tensor<bf16, Cpu> wb({s.N, s.K});
      for (std::int64_t i = 0; i < wf.numel(); ++i) wb.data()[i] = bf16(wf.data()[i]);
      Tensor<float, Cpu> y({s.M, s.N});
      const double gflop = 2.0 * double(s.M) * double(s.N) * double(s.K) / 1e9;
      for (const auto& w : o.weights) {
        const auto run = [&] {
          if (w == "f32") cpu::linear<float>(ctx, x.data(), s.K, wf.data(), nullptr, y.data(), s.N, s.M, s.N, s.K);
          else cpu::linear<bf16>(ctx, x.data(), s.K, wb.data(), nullptr, y.data(), s.N, s.M, s.N, s.K);
        };
        emit(std::string("gemm:") + s.what, w, threads, gflop, measure(run, o.repeats, o.warmup));
      }
    }
    // DC-AE decoder, highest resolution stage: 3x3 conv 128 -> 128 at 128x256.
    const Conv2dShape cs{1, 128, o.dcae_h, o.dcae_w, 128, 3, 1};
    const auto in = randn({1, 128, o.dcae_h, o.dcae_w}, 10), wt = randn({128, 128, 3, 3}, 11, 0.03f);
    Tensor<float, Cpu> out({1, 128, o.dcae_h, o.dcae_w});
    emit("conv3x3_128", "f32", threads, 2.0 * 9 * 128 * 128 * double(o.dcae_h * o.dcae_w) / 1e9,
         measure([&] { cpu::conv2d(ctx, in.data(), wt.data(), nullptr, out.data(), cs); }, o.repeats, o.warmup));
  }
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Options o = parse(argc, argv);
    const auto& f = cpu::cpu_features();
    std::printf("{\"name\": \"machine\", \"cpu\": \"%s\", \"hardware_threads\": %d, \"best_isa\": \"%s\", "
                "\"active_isa\": \"%s\", \"tile\": \"%s\", \"avx512\": %s, \"avx512_bf16\": %s, \"amx_bf16\": %s}\n",
                cpu_model_name().c_str(), hardware_threads(), cpu::isa_name(f.best()), cpu::isa_name(cpu::active_isa()),
                tile_name(), f.avx512 ? "true" : "false", f.avx512_bf16 ? "true" : "false", f.amx_bf16 ? "true" : "false");
    std::fflush(stdout);
    if (o.wants("gemm2048")) bench_gemm(o);
    if (o.wants("gemm_shapes")) bench_gemm_shapes(o);
    for (const auto& w : o.weights) {
      if (o.wants("mst") || o.wants("traj_eval") || o.wants("vis_eval")) {
        if (w == "f32") bench_world<float>(o, w);
        else bench_world<bf16>(o, w);
      }
      if (o.wants("dcae_decode") && w == "f32") bench_dcae<float>(o, w);  // the DC-AE is compared in float32
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_cpu_bench_mid: %s\n", e.what());
    return 1;
  }
  return 0;
}
