// DC-AE f32c32 on the CPU at the real widths/depths (DcaeConfig defaults, random weights) and a
// reduced image (default 128x256; EPONA_DCAE_BENCH_HW="H,W" changes it): encode, single-frame
// decode, and a clip decode of condition_frames frames, with GFLOP/s counted as spec §12
// (dcae_flops). Also the hottest layer shape alone — a 3x3 conv 512 -> 512 (decoder stage 2) —
// next to the plain Eigen GEMM of the same size, to show the im2col overhead.
// Counters: GFLOP/s over wall time, and GFLOP per CPU-second of the whole process (all threads):
// on a shared machine the second tells the kernels' efficiency when the wall clock cannot.
// EPONA_THREADS sets the thread count (default: all hardware threads).
#include <benchmark/benchmark.h>

#include <Eigen/Core>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <random>
#include <sys/resource.h>

#include "epona/cpu/context.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/model/dcae.hpp"

using namespace epona;
using HostTensor = Tensor<float, Cpu>;

namespace {

std::pair<std::int64_t, std::int64_t> bench_size() {
  std::int64_t h = 128, w = 256;
  if (const char* env = std::getenv("EPONA_DCAE_BENCH_HW")) std::sscanf(env, "%ld,%ld", &h, &w);
  return {h, w};
}

HostTensor random_tensor(const Shape& shape, std::uint64_t seed) {
  HostTensor t(shape);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = u(rng);
  return t;
}

cpu::Context& context() {
  static cpu::Context ctx(std::getenv("EPONA_THREADS") ? std::atoi(std::getenv("EPONA_THREADS")) : 0);
  return ctx;
}

double process_cpu_seconds() {
  rusage r{};
  getrusage(RUSAGE_SELF, &r);
  return double(r.ru_utime.tv_sec + r.ru_stime.tv_sec) + 1e-6 * double(r.ru_utime.tv_usec + r.ru_stime.tv_usec);
}

// Runs `body` once per benchmark iteration and reports the counters.
template <class Body>
void run(benchmark::State& state, double flops_per_iteration, Body body) {
  const double cpu0 = process_cpu_seconds();
  for (auto _ : state) body();
  const double cpu = process_cpu_seconds() - cpu0;
  const double iterations = double(state.iterations());
  state.counters["GFLOP"] = flops_per_iteration / 1e9;
  state.counters["GFLOP/s"] = benchmark::Counter(flops_per_iteration / 1e9, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["GFLOP/cpu-s"] = cpu > 0 ? flops_per_iteration * iterations / cpu / 1e9 : 0;
  state.counters["threads"] = context().threads();
}

const Dcae<Cpu, float>& shared_dcae() {
  static const std::unique_ptr<Dcae<Cpu, float>> m = [] {
    auto p = std::make_unique<Dcae<Cpu, float>>(DcaeConfig{});
    p->randomize(1);
    return p;
  }();
  return *m;
}

void BM_DcaeEncode(benchmark::State& state) {
  const auto [h, w] = bench_size();
  const HostTensor image = random_tensor({1, 3, h, w}, 2);
  run(state, dcae_flops(shared_dcae().config(), h, w).encode,
      [&] { benchmark::DoNotOptimize(shared_dcae().encode(context(), image).data()); });
}

void BM_DcaeDecodeFrame(benchmark::State& state) {
  const auto [h, w] = bench_size();
  const HostTensor z = random_tensor({1, 32, h / 32, w / 32}, 3);
  run(state, dcae_flops(shared_dcae().config(), h, w, 1).decode_total(),
      [&] { benchmark::DoNotOptimize(shared_dcae().decode(context(), z, false).data()); });
}

void BM_DcaeDecodeClip(benchmark::State& state) {
  const auto [h, w] = bench_size();
  const std::int64_t frames = shared_dcae().config().condition_frames;
  const HostTensor z = random_tensor({frames, 32, h / 32, w / 32}, 4);
  run(state, double(frames) * dcae_flops(shared_dcae().config(), h, w, frames).decode_total(),
      [&] { benchmark::DoNotOptimize(shared_dcae().decode(context(), z, true).data()); });
}

// Decoder stage 2 at the bench size: 512 -> 512 channels, 3x3, at (H/4, W/4).
void BM_Conv3x3_512(benchmark::State& state) {
  const auto [h, w] = bench_size();
  const Conv2dShape s{1, 512, h / 4, w / 4, 512, 3, 1};
  const HostTensor x = random_tensor({1, 512, s.height, s.width}, 5), wt = random_tensor({512, 512, 3, 3}, 6),
                   b = random_tensor({512}, 7);
  HostTensor y({1, 512, s.height, s.width});
  run(state, 2.0 * 9 * 512 * 512 * double(s.height * s.width),
      [&] { cpu::conv2d(context(), x.data(), wt.data(), b.data(), y.data(), s); });
}

// The same multiply without im2col: (512 x 4608) · (4608 x HW/16).
void BM_Gemm_512x4608(benchmark::State& state) {
  const auto [h, w] = bench_size();
  const std::int64_t P = h / 4 * (w / 4), K = 512 * 9;
  using Mat = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  const Mat A = Mat::Random(512, K), B = Mat::Random(K, P);
  Mat C(512, P);
  context();
  run(state, 2.0 * 512 * double(K) * double(P), [&] {
    C.noalias() = A * B;
    benchmark::DoNotOptimize(C.data());
  });
}

}  // namespace

BENCHMARK(BM_Gemm_512x4608)->Unit(benchmark::kMillisecond)->MinTime(1.0)->UseRealTime();
BENCHMARK(BM_Conv3x3_512)->Unit(benchmark::kMillisecond)->MinTime(1.0)->UseRealTime();
BENCHMARK(BM_DcaeEncode)->Unit(benchmark::kSecond)->MinTime(1.0)->UseRealTime();
BENCHMARK(BM_DcaeDecodeFrame)->Unit(benchmark::kSecond)->MinTime(1.0)->UseRealTime();
BENCHMARK(BM_DcaeDecodeClip)->Unit(benchmark::kSecond)->MinTime(1.0)->UseRealTime();

BENCHMARK_MAIN();
