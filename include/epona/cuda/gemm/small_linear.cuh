// epona/cuda/gemm/small_linear.cuh — Linear layers too small for cuBLASLt's tiles: y = x · Wᵀ + b
// with a few outputs per row (the TrajDiT's final layer: 15 x 3 outputs of K = 1024, which
// cuBLASLt runs as a 14 µs GEMV-like kernel) or a tiny inner dimension (its input layer: K = 3,
// a legacy unaligned kernel). A warp per output (lanes split K, float32 sums) or a thread per
// output (tiny K); bias added in float32 and one rounding, as cuBLASLt's bias epilogue.
// Products of 2 to 16 rows with K >= 4096 go to the skinny-M kernel (skinny_linear.cuh).
#pragma once

#include <cstdint>

#include "epona/core/kernel_options.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/gemm/skinny_linear.cuh"

namespace epona::cuda {

namespace detail {

// One warp per output (m, n); with Packed, lanes take 8-element packs of the row (K % 8 == 0,
// rows 16-byte aligned), else single elements.
template <class T, bool Packed>
__global__ void small_linear_warp_kernel(LinearArgs<T> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;
  if (item >= std::int64_t{a.M} * a.N) return;
  const int lane = threadIdx.x & 31, m = static_cast<int>(item / a.N), n = static_cast<int>(item % a.N);
  const T* xr = a.x + m * a.ldx;
  const T* wr = a.w + std::int64_t{n} * a.K;
  float acc = 0;
  if constexpr (Packed) {
    for (int p = lane * kPack; p < a.K; p += 32 * kPack) {
      float xs[kPack], ws[kPack];
      load8(xr + p, xs);
      load8(wr + p, ws);
#pragma unroll
      for (int i = 0; i < kPack; ++i) acc = fmaf(xs[i], ws[i], acc);
    }
  } else {
    for (int k = lane; k < a.K; k += 32) acc = fmaf(to_f32(xr[k]), to_f32(wr[k]), acc);
  }
  acc = warp_sum(acc);
  if (lane == 0) a.y[m * a.ldy + n] = from_f32<T>(a.bias ? acc + to_f32(a.bias[n]) : acc);
}

// One thread per output, for a tiny K.
template <class T>
__global__ void small_linear_thread_kernel(LinearArgs<T> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x;
  if (item >= std::int64_t{a.M} * a.N) return;
  const int m = static_cast<int>(item / a.N), n = static_cast<int>(item % a.N);
  const T* xr = a.x + m * a.ldx;
  const T* wr = a.w + std::int64_t{n} * a.K;
  float acc = 0;
  for (int k = 0; k < a.K; ++k) acc = fmaf(to_f32(xr[k]), to_f32(wr[k]), acc);
  a.y[m * a.ldy + n] = from_f32<T>(a.bias ? acc + to_f32(a.bias[n]) : acc);
}

// Where the small kernels run instead of cuBLASLt (measured on the H200: the TrajDiT's 15 x 3
// x 1024 final layer took 14.4 µs in cuBLASLt's GEMV kernel, its 15 x 1024 x 3 input layer 5 µs
// in a legacy unaligned kernel).
constexpr std::int64_t kSmallKMax = 16, kFewOutputsMax = 16, kFewOutputsItems = 4096, kTinyKItems = 1 << 20;

// The warp-per-output or thread-per-output kernel for those shapes (no epilogue); false
// (nothing launched) for other shapes.
template <class T>
bool few_outputs_linear(Context& ctx, const LinearArgs<T>& a) {
  const std::int64_t items = std::int64_t{a.M} * a.N;
  constexpr int threads = 256;
  if (a.K <= kSmallKMax && items <= kTinyKItems) {
    launch_after(small_linear_thread_kernel<T>, static_cast<unsigned>((items + threads - 1) / threads), threads, 0,
                 ctx, a);
  } else if (a.N <= kFewOutputsMax && items <= kFewOutputsItems) {
    const unsigned blocks = static_cast<unsigned>((items + threads / 32 - 1) / (threads / 32));
    if (packable(a.x, a.K, a.ldx) && packable(a.w, a.K, a.K))
      launch_after(small_linear_warp_kernel<T, true>, blocks, threads, 0, ctx, a);
    else
      launch_after(small_linear_warp_kernel<T, false>, blocks, threads, 0, ctx, a);
  } else {
    return false;
  }
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

// Runs y = act(x · wᵀ + bias) with one of our kernels when the product has one of those shapes
// (epilogue none) or is skinny where that kernel wins (skinny_wins: 2-16 rows, K >= 4096; none
// or the tanh GELU); false (nothing launched) otherwise.
template <class T>
bool small_linear(Context& ctx, const T* x, std::int64_t ldx, const T* w, const T* bias, T* y, std::int64_t ldy,
                  std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi) {
  if (M > 0x7fffffff || N > 0x7fffffff || K > 0x7fffffff) return false;
  const LinearArgs<T> a{x, ldx, w, bias, y, ldy, static_cast<int>(M), static_cast<int>(N), static_cast<int>(K)};
  if (epi == Epilogue::None && few_outputs_linear(ctx, a)) return true;
  return ctx.policy().skinny_linear && skinny_wins(M, K) && skinny_linear(ctx, a, epi);
}

}  // namespace detail
}  // namespace epona::cuda
