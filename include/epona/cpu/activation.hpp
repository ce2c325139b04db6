// epona/cpu/activation.hpp — element-wise activations, in place: exact GELU (erf, MST and
// nn.GELU()), tanh-approximated GELU (the DiTs' MLPs) and SiLU.
#pragma once

#include <cmath>
#include <cstdint>

#include "epona/cpu/context.hpp"

namespace epona::cpu {

inline void gelu_erf(Context&, float* x, std::int64_t n) {
#pragma omp parallel for
  for (std::int64_t i = 0; i < n; ++i) x[i] = 0.5f * x[i] * (1.0f + std::erf(x[i] * 0.70710678118654752f));
}

inline void gelu_tanh(Context&, float* x, std::int64_t n) {
  constexpr float k = 0.7978845608028654f;  // sqrt(2/pi)
#pragma omp parallel for
  for (std::int64_t i = 0; i < n; ++i) {
    const float v = x[i];
    x[i] = 0.5f * v * (1.0f + std::tanh(k * (v + 0.044715f * v * v * v)));
  }
}

inline void silu(Context&, float* x, std::int64_t n) {
#pragma omp parallel for
  for (std::int64_t i = 0; i < n; ++i) x[i] = x[i] / (1.0f + std::exp(-x[i]));
}

// y = silu(x) into a separate buffer (modulation inputs keep the original vector).
inline void silu_to(Context&, const float* x, float* y, std::int64_t n) {
  for (std::int64_t i = 0; i < n; ++i) y[i] = x[i] / (1.0f + std::exp(-x[i]));
}

}  // namespace epona::cpu
