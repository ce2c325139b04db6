// epona/cpu/residual_norm.hpp — a residual update followed by the LayerNorm after it, the CPU
// side of the GPU's fused pass (epona/cuda/pointwise/norm.cuh): x += [gate ⊙] y, then LN(x) affine (the
// MST's residual and ln2 / next ln1) or modulated (the DiT blocks). Here the two steps simply
// run in turn, so both backends compute the same function.
#pragma once

#include <cstdint>

#include "epona/cpu/context.hpp"
#include "epona/cpu/elementwise.hpp"
#include "epona/cpu/norm.hpp"

namespace epona::cpu {

// x[r, :] += y[r, :], then out[r, :] = LN(x[r, :]) * weight + bias (weight/bias may be null).
inline void add_layer_norm(Context& ctx, float* x, const float* y, float* out, std::int64_t rows, std::int64_t n,
                           const float* weight, const float* bias, float eps) {
  add_inplace(ctx, x, y, rows * n);
  layer_norm(ctx, x, out, rows, n, weight, bias, eps);
}

// x[r, :] += gate[:] * y[r, :], then out = (1 + scale) * LN(x) + shift.
inline void add_gated_layer_norm_modulate(Context& ctx, float* x, const float* y, const float* gate, float* out,
                                          std::int64_t rows, std::int64_t n, const float* shift, const float* scale,
                                          float eps) {
  add_gated(ctx, x, y, gate, rows, n);
  layer_norm_modulate(ctx, x, out, rows, n, shift, scale, eps);
}

}  // namespace epona::cpu
