// epona/cpu/copy_fill_axpy.hpp — the plain CPU kernels the world-model layers need beyond the
// cpu/ op contract: copies (dense and strided 2-D), fill, and the Euler update x += a·v. Plain
// loops in namespace epona::cpu so layer code finds them by ADL like the other kernels; the GPU's
// counterparts are in cuda/pointwise/copy_convert_axpy.cuh.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>

#include "epona/cpu/context.hpp"

namespace epona::cpu {

inline void copy(Context&, const float* src, float* dst, std::int64_t n) {
  if (n > 0 && src != dst) std::memmove(dst, src, static_cast<std::size_t>(n) * sizeof(float));
}

// dst[r * dst_stride + c] = src[r * src_stride + c] for r < rows, c < cols (non-overlapping).
inline void copy_rows(Context&, const float* src, std::int64_t src_stride, float* dst, std::int64_t dst_stride,
                      std::int64_t rows, std::int64_t cols) {
#pragma omp parallel for if (rows * cols > 65536)
  for (std::int64_t r = 0; r < rows; ++r)
    std::memcpy(dst + r * dst_stride, src + r * src_stride, static_cast<std::size_t>(cols) * sizeof(float));
}

inline void fill(Context&, float* x, float value, std::int64_t n) { std::fill_n(x, n, value); }

// x += a * v, the product rounded to float before the add (PyTorch's `x + dt * v` runs the
// multiply and the add as two kernels; keep them two roundings).
inline void axpy(Context&, float* x, const float* v, float a, std::int64_t n) {
  for (std::int64_t i = 0; i < n; ++i) {
    volatile float step = a * v[i];
    x[i] += step;
  }
}

}  // namespace epona::cpu
