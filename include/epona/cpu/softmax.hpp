// epona/cpu/softmax.hpp — numerically safe softmax over the last dimension, in place:
// exp(x − max) / Σ exp(x − max) (torch.softmax), except that a row that is entirely −inf
// (fully masked) becomes zeros instead of NaN, the convention of the attention kernels.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "epona/cpu/context.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

namespace detail {
inline float row_max(const float* x, std::int64_t n) {
  constexpr float ninf = -std::numeric_limits<float>::infinity();
  simd::Batch m(ninf);
  std::int64_t i = 0;
  for (; i + simd::kWidth <= n; i += simd::kWidth) m = xsimd::max(m, simd::load(x + i));
  if (i < n) m = xsimd::max(m, simd::load_partial(x + i, n - i, ninf));
  return simd::reduce_max(m);
}

inline void softmax_row(float* x, std::int64_t n) {
  using simd::Batch;
  const float mx = row_max(x, n);
  if (mx == -std::numeric_limits<float>::infinity()) {  // fully masked (or empty) row
    simd::map(n, x, [](const Batch&) { return Batch(0.f); }, x);
    return;
  }
  const Batch m(mx);
  simd::map(n, x, [m](const Batch& v) { return xsimd::exp(v - m); }, x);
  const Batch inv(1.0f / simd::sum(x, n));
  simd::map(n, x, [inv](const Batch& v) { return v * inv; }, x);
}
}  // namespace detail

// x: (rows, n), each row replaced by its softmax.
inline void softmax_rows(Context&, float* x, std::int64_t rows, std::int64_t n) {
  simd::for_each_row(rows, n, [=](std::int64_t r) { detail::softmax_row(x + r * n, n); });
}

}  // namespace epona::cpu
