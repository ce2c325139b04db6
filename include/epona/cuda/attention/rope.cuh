// epona/cuda/attention/rope.cuh — rotary position embedding on the GPU with interleaved pairs
// (channels 2j, 2j+1 form one complex number), as both the MST and the DiTs apply it, in
// place on strided heads (packed QKV). cos/sin tables (rows, head_dim/2) float32, shared by heads.
#pragma once

#include <cstdint>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace detail {

// One thread per (token, head, pair); float32 arithmetic, result rounded to T (as the official
// `.type_as(x)` after the float32 rotation).
template <class T>
__global__ void rope_kernel(T* x, std::int64_t rows, std::int64_t row_stride, int heads, int head_dim,
                            const float* cos, const float* sin) {
  const int pairs = head_dim / 2;
  const std::int64_t per_row = std::int64_t{heads} * pairs, total = rows * per_row;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::int64_t r = i / per_row;
    const int within = static_cast<int>(i - r * per_row);
    const int h = within / pairs, j = within - h * pairs;
    T* p = x + r * row_stride + h * head_dim + 2 * j;
    const float c = cos[r * pairs + j], s = sin[r * pairs + j];
    const float a = to_f32(p[0]), b = to_f32(p[1]);
    p[0] = from_f32<T>(c * a - s * b);
    p[1] = from_f32<T>(s * a + c * b);
  }
}

}  // namespace detail

// In place on `rows` tokens whose heads start at x + r * row_stride (heads side by side).
template <class T>
void apply_rope(Context& ctx, T* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                std::int64_t head_dim, const float* cos, const float* sin) {
  static_assert(is_device_float<T>, "apply_rope takes float or bf16");
  EPONA_CHECK(rows >= 0 && heads > 0 && head_dim > 0 && head_dim % 2 == 0 && head_dim <= 0x7fffffff &&
                  heads <= 0x7fffffff,
              "apply_rope: bad extent (rows ", rows, ", heads ", heads, ", head_dim ", head_dim,
              "; head_dim must be even)");
  EPONA_CHECK(row_stride >= heads * head_dim, "apply_rope: row stride ", row_stride, " is narrower than ", heads,
              " heads of ", head_dim);
  EPONA_CHECK(cos != nullptr && sin != nullptr, "apply_rope: null table");
  const std::int64_t total = rows * heads * (head_dim / 2);
  if (total == 0) return;
  detail::rope_kernel<<<detail::grid_for(total, 256), 256, 0, ctx.stream()>>>(
      x, rows, row_stride, static_cast<int>(heads), static_cast<int>(head_dim), cos, sin);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda
