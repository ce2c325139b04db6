// epona/cpu/qk_rms_norm_rope.hpp — the DiTs' per-head QK RMSNorm followed by rotary embedding on
// the CPU (rms_norm_heads then apply_rope, composed), the counterpart of the GPU's one-pass
// cuda/attention/qk_rms_norm_rope.cuh. In namespace epona::cpu so layer code finds it by ADL.
#pragma once

#include <cstdint>

#include "epona/cpu/context.hpp"
#include "epona/cpu/norm.hpp"
#include "epona/cpu/rope.hpp"

namespace epona::cpu {

// Per head RMSNorm of `rows` tokens (heads at x + r·row_stride), then their rotation by rows r
// of the cos/sin tables (rows, head_dim/2).
inline void rms_norm_rope_heads(Context& ctx, float* x, std::int64_t rows, std::int64_t row_stride,
                                std::int64_t heads, std::int64_t head_dim, const float* scale, float eps,
                                const float* cos, const float* sin) {
  rms_norm_heads(ctx, x, rows, row_stride, heads, head_dim, scale, eps);
  apply_rope(ctx, x, rows, row_stride, heads, head_dim, cos, sin);
}

}  // namespace epona::cpu
