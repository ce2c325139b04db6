// epona/cuda/elementwise.cuh — residual and gating updates between the big GEMMs on the GPU:
// x += y, x += gate ⊙ y (gate broadcast over rows: adaLN's gated residual) and a row broadcast
// add. Mixed storage types round like PyTorch's promotion (bf16 ⊙ bf16 rounds to bf16 first).
#pragma once

#include <cstdint>

#include "epona/cuda/context.hpp"
#include "epona/cuda/device.cuh"

namespace epona::cuda {

namespace detail {

template <class TX, class TY>
__global__ void add_kernel(TX* x, const TY* y, std::int64_t n) {
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < n;
       i += std::int64_t{gridDim.x} * blockDim.x)
    x[i] = from_f32<TX>(to_f32(x[i]) + to_f32(y[i]));
}

// x[r, c] += gate[c] * y[r, c]; with y null, x[r, c] += gate[c] (the row broadcast add).
template <class TX, class TY, class TG>
__global__ void add_gated_kernel(TX* x, const TY* y, const TG* gate, std::int64_t rows, std::int64_t n) {
  const std::int64_t total = rows * n;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const float g = to_f32(gate[i % n]);
    const float update = y ? round_to<promote_t<TG, TY>>(g * to_f32(y[i])) : g;
    x[i] = from_f32<TX>(to_f32(x[i]) + update);
  }
}

inline void check_count(std::int64_t rows, std::int64_t n, const char* what) {
  EPONA_CHECK(rows >= 0 && n >= 0, what, ": negative extent (rows ", rows, ", width ", n, ")");
}

}  // namespace detail

// x[i] += y[i] for i < n.
template <class TX, class TY>
void add_inplace(Context& ctx, TX* x, const TY* y, std::int64_t n) {
  static_assert(is_device_float<TX> && is_device_float<TY>, "add_inplace takes float or bf16");
  detail::check_count(1, n, "add_inplace");
  if (n == 0) return;
  detail::add_kernel<<<detail::grid_for(n, 256), 256, 0, ctx.stream()>>>(x, y, n);
  EPONA_CUDA_CHECK_LAUNCH();
}

// x[r, :] += gate[:] * y[r, :] for rows of width n.
template <class TX, class TY, class TG>
void add_gated(Context& ctx, TX* x, const TY* y, const TG* gate, std::int64_t rows, std::int64_t n) {
  static_assert(is_device_float<TX> && is_device_float<TY> && is_device_float<TG>, "add_gated takes float or bf16");
  detail::check_count(rows, n, "add_gated");
  EPONA_CHECK(y != nullptr && gate != nullptr, "add_gated: null input");
  if (rows * n == 0) return;
  detail::add_gated_kernel<<<detail::grid_for(rows * n, 256), 256, 0, ctx.stream()>>>(x, y, gate, rows, n);
  EPONA_CUDA_CHECK_LAUNCH();
}

// x[r, :] += b[:] for rows of width n.
template <class TX, class TB>
void add_row_broadcast(Context& ctx, TX* x, const TB* b, std::int64_t rows, std::int64_t n) {
  static_assert(is_device_float<TX> && is_device_float<TB>, "add_row_broadcast takes float or bf16");
  detail::check_count(rows, n, "add_row_broadcast");
  EPONA_CHECK(b != nullptr, "add_row_broadcast: null bias");
  if (rows * n == 0) return;
  detail::add_gated_kernel<<<detail::grid_for(rows * n, 256), 256, 0, ctx.stream()>>>(
      x, static_cast<const TX*>(nullptr), b, rows, n);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda
