// Shared helpers of the DC-AE GPU tests (tests/cuda/dcae_*.cu): NCHW <-> channels-last on the
// host, the error bounds of bf16 paths, and a switch that poisons every buffer the model code
// allocates on the GPU (so an element nobody writes shows as NaN even in reused pool memory),
// and the programs' GPU and CPU contexts.
#pragma once

#include <cstdint>
#include <string>

#include "cuda_test_util.cuh"
#include "epona/cpu/context.hpp"
#include "epona/cuda/dcae_ops.cuh"
#include "epona/nn/feature_map.hpp"

namespace epona::test {

// The process-wide contexts of a test program: one GPU context, one CPU context (references).
inline cuda::Context& gpu() {
  static cuda::Context ctx;
  return ctx;
}
inline cpu::Context& host() {
  static cpu::Context ctx;
  return ctx;
}

// (N, C, H, W) host values -> (N, H, W, C), and back.
inline HostF to_nhwc(const HostF& x) {
  const std::int64_t N = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3), HW = H * W;
  HostF y({N, H, W, C});
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t c = 0; c < C; ++c)
      for (std::int64_t p = 0; p < HW; ++p) y.data()[(n * HW + p) * C + c] = x.data()[(n * C + c) * HW + p];
  return y;
}
inline HostF to_nchw(const HostF& y) {
  const std::int64_t N = y.size(0), H = y.size(1), W = y.size(2), C = y.size(3), HW = H * W;
  HostF x({N, C, H, W});
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t c = 0; c < C; ++c)
      for (std::int64_t p = 0; p < HW; ++p) x.data()[(n * C + c) * HW + p] = y.data()[(n * HW + p) * C + c];
  return x;
}

// A host NCHW map uploaded as a channels-last device map of T (values converted to T).
template <class T>
Dev<T> upload_map(cuda::Context& ctx, const HostF& nchw) {
  return upload<T>(ctx, to_nhwc(nchw));
}
// A channels-last device map downloaded as host NCHW float.
template <class T>
HostF download_map(cuda::Context& ctx, const Dev<T>& nhwc) {
  return to_nchw(download(ctx, nhwc));
}

// bf16 errors of a chain of operations (a block, a model stage): twice the per-stage error of
// the official recipe under bf16 autocast (golden README, "DCAE in bf16": 1e-2 .. 2e-2 rel_max).
inline Bound bf16_stage_bound(double max_ref) { return {2e-2, 4e-2 * max_ref}; }

template <class T>
Bound stage_bound(double max_ref) {
  if constexpr (std::is_same_v<T, float>) return {kF32Tol, kF32Tol * max_ref};
  return bf16_stage_bound(max_ref);
}

// Poisons every scratch/result buffer gpu() hands out while alive (tests only).
struct PoisonBuffers : ScopedPolicy<bool> {
  PoisonBuffers() : ScopedPolicy(gpu().policy().poison_new_buffers, true) {}
};

// The engine of gpu()'s dense convolutions.
struct UseEngine : ScopedPolicy<cuda::ConvEngine> {
  explicit UseEngine(cuda::ConvEngine e) : ScopedPolicy(gpu().policy().conv_engine, e) {}
};
// gpu()'s fused conv epilogues. BatchNorm folding happens at bind time, before any context, and
// follows the environment (EPONA_CUDA_CONV_FUSE); folded or not, a block computes the same.
struct UseFusion : ScopedPolicy<bool> {
  explicit UseFusion(bool on) : ScopedPolicy(gpu().policy().conv_fusion, on) {}
};
// gpu()'s DC-AE fused kernels (temporal blocks, upsampling pair).
struct UseDcaeFusion : ScopedPolicy<bool> {
  explicit UseDcaeFusion(bool on) : ScopedPolicy(gpu().policy().dcae_fusion, on) {}
};

inline const char* engine_name(cuda::ConvEngine e) {
  return e == cuda::ConvEngine::Gemm ? "gemm" : e == cuda::ConvEngine::Cudnn ? "cudnn" : "auto";
}

}  // namespace epona::test
