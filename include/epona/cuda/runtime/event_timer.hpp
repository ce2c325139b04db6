// epona/cuda/runtime/event_timer.hpp — times work enqueued on a context's stream with CUDA events: the
// one timing loop behind the library's measured choices (the DC-AE's convolution engine) and
// the GPU benchmarks (benchmarks/gpu_event_timer.cuh adds their warm-up).
#pragma once

#include <cuda_runtime.h>

#include <vector>

#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"

namespace epona::cuda {

// Milliseconds between two events around each of `repeats` calls of f (which enqueues work on
// ctx's stream). The events are released even if f throws.
template <class F>
std::vector<float> event_times_ms(Context& ctx, int repeats, const F& f) {
  struct Events {
    cudaEvent_t start = nullptr, stop = nullptr;
    ~Events() {
      if (start) cudaEventDestroy(start);
      if (stop) cudaEventDestroy(stop);
    }
  } e;
  EPONA_CUDA_CHECK(cudaEventCreate(&e.start));
  EPONA_CUDA_CHECK(cudaEventCreate(&e.stop));
  std::vector<float> runs;
  runs.reserve(repeats > 0 ? repeats : 0);
  for (int i = 0; i < repeats; ++i) {
    EPONA_CUDA_CHECK(cudaEventRecord(e.start, ctx.stream()));
    f();
    EPONA_CUDA_CHECK(cudaEventRecord(e.stop, ctx.stream()));
    EPONA_CUDA_CHECK(cudaEventSynchronize(e.stop));
    float ms = 0;
    EPONA_CUDA_CHECK(cudaEventElapsedTime(&ms, e.start, e.stop));
    runs.push_back(ms);
  }
  return runs;
}

}  // namespace epona::cuda
