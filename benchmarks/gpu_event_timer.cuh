// benchmarks/gpu_event_timer.cuh — times work enqueued on a context's stream with CUDA events
// after a warm-up (bench_gpu_world, bench_gpu_dcae, bench_gpu_batch), through the library's
// event_timer.hpp, and the bf16 GEMM ceiling the roofline fractions are taken against.
#pragma once

#include <functional>
#include <vector>

#include "epona/core/rng.hpp"
#include "epona/cuda/backend.cuh"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/event_timer.hpp"
#include "bench_stats.hpp"

namespace epona::bench {

// Milliseconds of `fn` (which enqueues on ctx's stream, possibly synchronising) between two
// events, `repeats` times after `warmup` calls.
inline std::vector<double> event_times_ms(cuda::Context& ctx, int repeats, int warmup, const std::function<void()>& fn) {
  for (int i = 0; i < warmup; ++i) fn();
  ctx.synchronize();
  const std::vector<float> runs = cuda::event_times_ms(ctx, repeats, fn);
  return {runs.begin(), runs.end()};
}

// The bf16 GEMM ceiling through epona's cuBLASLt path: 8192^3, operands rotating over buffers
// larger than L2.
inline double gemm_ceiling_tflops(cuda::Context& ctx) {
  constexpr std::int64_t n = 8192;
  constexpr int sets = 2;
  std::vector<Tensor<bf16, Cuda>> x, w, y;
  TorchGenerator gen(3);
  auto host = gen.randn({n, n});
  Tensor<bf16, Cpu> hb(host.shape());
  for (std::int64_t i = 0; i < hb.numel(); ++i) hb.data()[i] = bf16(host.data()[i]);
  for (int s = 0; s < sets; ++s) {
    x.push_back(cuda::to_device(ctx, hb));
    w.push_back(cuda::to_device(ctx, hb));
    y.emplace_back(Shape{n, n});
  }
  const Tensor<bf16, Cuda> none;
  int k = 0;
  const auto runs = event_times_ms(ctx, 10, 3, [&] {
    cuda::linear(ctx, x[k % sets], w[k % sets], none, y[k % sets]);
    ++k;
  });
  return 2.0 * n * n * n / (bench::median(runs) * 1e-3) / 1e12;
}

}  // namespace epona::bench
