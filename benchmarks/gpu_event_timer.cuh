// benchmarks/gpu_event_timer.cuh — times work enqueued on a context's stream with CUDA events:
// the one timing loop of the GPU benchmarks (bench_gpu_world, bench_gpu_dcae).
#pragma once

#include <cuda_runtime.h>

#include <functional>
#include <vector>

#include "epona/cuda/context.hpp"

namespace epona::bench {

// Milliseconds of `fn` (which enqueues on ctx's stream, possibly synchronising) between two
// events, `repeats` times after `warmup` calls.
inline std::vector<double> event_times_ms(cuda::Context& ctx, int repeats, int warmup, const std::function<void()>& fn) {
  for (int i = 0; i < warmup; ++i) fn();
  ctx.synchronize();
  cudaEvent_t a, b;
  EPONA_CUDA_CHECK(cudaEventCreate(&a));
  EPONA_CUDA_CHECK(cudaEventCreate(&b));
  std::vector<double> runs;
  for (int i = 0; i < repeats; ++i) {
    EPONA_CUDA_CHECK(cudaEventRecord(a, ctx.stream()));
    fn();
    EPONA_CUDA_CHECK(cudaEventRecord(b, ctx.stream()));
    EPONA_CUDA_CHECK(cudaEventSynchronize(b));
    float ms = 0;
    EPONA_CUDA_CHECK(cudaEventElapsedTime(&ms, a, b));
    runs.push_back(ms);
  }
  EPONA_CUDA_CHECK(cudaEventDestroy(a));
  EPONA_CUDA_CHECK(cudaEventDestroy(b));
  return runs;
}

}  // namespace epona::bench
