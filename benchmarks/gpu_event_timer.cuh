// benchmarks/gpu_event_timer.cuh — times work enqueued on a context's stream with CUDA events
// after a warm-up (bench_gpu_world, bench_gpu_dcae), through the library's event_timer.hpp.
#pragma once

#include <functional>
#include <vector>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/event_timer.hpp"

namespace epona::bench {

// Milliseconds of `fn` (which enqueues on ctx's stream, possibly synchronising) between two
// events, `repeats` times after `warmup` calls.
inline std::vector<double> event_times_ms(cuda::Context& ctx, int repeats, int warmup, const std::function<void()>& fn) {
  for (int i = 0; i < warmup; ++i) fn();
  ctx.synchronize();
  const std::vector<float> runs = cuda::event_times_ms(ctx, repeats, fn);
  return {runs.begin(), runs.end()};
}

}  // namespace epona::bench
