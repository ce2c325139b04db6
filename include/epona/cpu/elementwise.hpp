// epona/cpu/elementwise.hpp — residual and gating updates used between the big GEMMs:
// x += y, x += gate ⊙ y (gate broadcast over rows: adaLN's gated residual), and a row
// broadcast add (time embeddings, biases).
#pragma once

#include <cstdint>

#include "epona/cpu/context.hpp"

namespace epona::cpu {

inline void add_inplace(Context&, float* x, const float* y, std::int64_t n) {
#pragma omp parallel for
  for (std::int64_t i = 0; i < n; ++i) x[i] += y[i];
}

// x[r, :] += gate[:] * y[r, :] for rows of width n.
inline void add_gated(Context&, float* x, const float* y, const float* gate, std::int64_t rows, std::int64_t n) {
#pragma omp parallel for
  for (std::int64_t r = 0; r < rows; ++r)
    for (std::int64_t i = 0; i < n; ++i) x[r * n + i] += gate[i] * y[r * n + i];
}

// x[r, :] += b[:] for rows of width n.
inline void add_row_broadcast(Context&, float* x, const float* b, std::int64_t rows, std::int64_t n) {
#pragma omp parallel for
  for (std::int64_t r = 0; r < rows; ++r)
    for (std::int64_t i = 0; i < n; ++i) x[r * n + i] += b[i];
}

}  // namespace epona::cpu
