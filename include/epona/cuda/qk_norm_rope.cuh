// epona/cuda/qk_norm_rope.cuh — the DiTs' per-head QK RMSNorm followed by rotary embedding in
// one pass (one warp per token and head, in place on packed QKV): the two kernels rms_norm_heads
// and apply_rope in sequence, with the same roundings — (x·rrms) rounded to the storage type,
// times the float32 scale, rounded (the official QKNorm), then the float32 rotation of the
// rounded pair, rounded again (`.type_as(x)`) — but one read and one write instead of two each.
#pragma once

#include <cstdint>

#include "epona/cuda/context.hpp"
#include "epona/cuda/device.cuh"

namespace epona::cuda {

namespace detail {

template <class T>
__global__ void rms_norm_rope_kernel(T* x, std::int64_t rows, std::int64_t row_stride, int heads, int head_dim,
                                     const float* scale, float eps, const float* cos, const float* sin) {
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;
  if (item >= rows * heads) return;
  const int lane = threadIdx.x & 31, pairs = head_dim / 2;
  const std::int64_t r = item / heads;
  T* p = x + r * row_stride + (item % heads) * head_dim;
  float ss = 0;
  for (int j = lane; j < pairs; j += 32) {
    const float a = to_f32(p[2 * j]), b = to_f32(p[2 * j + 1]);
    ss += a * a + b * b;
  }
  const float rr = 1.0f / sqrtf(warp_sum(ss) / static_cast<float>(head_dim) + eps);
  const float* cr = cos + r * pairs;
  const float* sr = sin + r * pairs;
  for (int j = lane; j < pairs; j += 32) {
    const float a = round_to<T>(round_to<T>(to_f32(p[2 * j]) * rr) * scale[2 * j]);
    const float b = round_to<T>(round_to<T>(to_f32(p[2 * j + 1]) * rr) * scale[2 * j + 1]);
    const float c = cr[j], s = sr[j];
    p[2 * j] = from_f32<T>(c * a - s * b);
    p[2 * j + 1] = from_f32<T>(s * a + c * b);
  }
}

}  // namespace detail

// In place on `rows` tokens whose heads start at x + r·row_stride: per head RMSNorm (eps, float32
// scale of head_dim) then the rotation by cos/sin rows r of (rows, head_dim/2) tables.
template <class T>
void rms_norm_rope_heads(Context& ctx, T* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                         std::int64_t head_dim, const float* scale, float eps, const float* cos, const float* sin) {
  static_assert(is_device_float<T>, "rms_norm_rope_heads takes float or bf16");
  EPONA_CHECK(rows >= 0 && heads > 0 && head_dim > 0 && head_dim % 2 == 0 && head_dim <= 0x7fffffff &&
                  heads <= 0x7fffffff,
              "rms_norm_rope_heads: bad extent (rows ", rows, ", heads ", heads, ", head_dim ", head_dim, ")");
  EPONA_CHECK(row_stride >= heads * head_dim, "rms_norm_rope_heads: row stride ", row_stride, " is narrower than ",
              heads, " heads of ", head_dim);
  EPONA_CHECK(scale != nullptr && cos != nullptr && sin != nullptr, "rms_norm_rope_heads: null scale or table");
  if (rows == 0) return;
  constexpr int threads = 256, warps = threads / 32;
  const std::int64_t blocks = (rows * heads + warps - 1) / warps;
  EPONA_CHECK(blocks <= 0x7fffffff, "rms_norm_rope_heads: ", rows * heads, " heads exceed one launch");
  detail::rms_norm_rope_kernel<<<static_cast<unsigned>(blocks), threads, 0, ctx.stream()>>>(
      x, rows, row_stride, static_cast<int>(heads), static_cast<int>(head_dim), scale, eps, cos, sin);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda
