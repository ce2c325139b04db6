// epona/cpu/elementwise.hpp — residual and gating updates used between the big GEMMs:
// x += y, x += gate ⊙ y (gate broadcast over rows: adaLN's gated residual), and a row
// broadcast add (time embeddings, biases). Vectorised with xsimd, rows shared among threads.
#pragma once

#include <cstdint>

#include "epona/cpu/context.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

inline void add_inplace(Context&, float* x, const float* y, std::int64_t n) {
  simd::parallel_map(n, x, [](const simd::Batch& a, const simd::Batch& b) { return a + b; }, x, y);
}

// x[r, :] += gate[:] * y[r, :] for rows of width n.
inline void add_gated(Context&, float* x, const float* y, const float* gate, std::int64_t rows, std::int64_t n) {
  simd::for_each_row(rows, n, [=](std::int64_t r) {
    float* xr = x + r * n;
    simd::map(n, xr, [](const simd::Batch& a, const simd::Batch& g, const simd::Batch& b) { return a + g * b; },
              xr, gate, y + r * n);
  });
}

// x[r, :] += b[:] for rows of width n.
inline void add_row_broadcast(Context&, float* x, const float* b, std::int64_t rows, std::int64_t n) {
  simd::for_each_row(rows, n, [=](std::int64_t r) {
    float* xr = x + r * n;
    simd::map(n, xr, [](const simd::Batch& a, const simd::Batch& c) { return a + c; }, xr, b);
  });
}

}  // namespace epona::cpu
