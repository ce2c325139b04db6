// epona/cpu/activation.hpp — element-wise activations, in place: exact GELU (erf, MST and
// nn.GELU()), tanh-approximated GELU (the DiTs' MLPs) and SiLU. Each is one batch functor
// (xsimd's erf/tanh/exp, a few ulp) so GEMM epilogues reuse the same code as the kernels.
#pragma once

#include <cstdint>

#include "epona/cpu/context.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

namespace act {
using simd::Batch;
// 0.5·x·(1 + erf(x/√2)), as torch's gelu(approximate='none').
struct GeluErf {
  Batch operator()(const Batch& x) const { return Batch(0.5f) * x * (Batch(1.f) + xsimd::erf(x * Batch(0.70710678118654752f))); }
};
// 0.5·x·(1 + tanh(√(2/π)·(x + 0.044715·x³))), as torch's gelu(approximate='tanh').
struct GeluTanh {
  Batch operator()(const Batch& x) const {
    const Batch inner = Batch(0.7978845608028654f) * (x + Batch(0.044715f) * x * x * x);
    return Batch(0.5f) * x * (Batch(1.f) + xsimd::tanh(inner));
  }
};
// x·sigmoid(x) = x / (1 + exp(-x)); exp overflow to +inf gives -0, as torch.
struct Silu {
  Batch operator()(const Batch& x) const { return x / (Batch(1.f) + xsimd::exp(-x)); }
};
}  // namespace act

inline void gelu_erf(Context&, float* x, std::int64_t n) { simd::parallel_map(n, x, act::GeluErf{}, x); }
inline void gelu_tanh(Context&, float* x, std::int64_t n) { simd::parallel_map(n, x, act::GeluTanh{}, x); }
inline void silu(Context&, float* x, std::int64_t n) { simd::parallel_map(n, x, act::Silu{}, x); }

// y = silu(x) into a separate buffer (modulation inputs keep the original vector).
inline void silu_to(Context&, const float* x, float* y, std::int64_t n) { simd::parallel_map(n, y, act::Silu{}, x); }

}  // namespace epona::cpu
