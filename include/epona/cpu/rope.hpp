// epona/cpu/rope.hpp — rotary position embedding with interleaved pairs (channels 2j, 2j+1
// form one complex number), as both the MST (2-D axial table) and the DiTs (3-axis table)
// apply it. The table is per token: cos/sin of shape (rows, head_dim/2), shared by all heads.
#pragma once

#include <algorithm>
#include <cstdint>

#include "epona/core/error.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

// In place on `rows` tokens whose heads start at x + r * row_stride (heads side by side):
// (x_2j, x_2j+1) <- (c·x_2j − s·x_2j+1, s·x_2j + c·x_2j+1) with c, s = cos[r, j], sin[r, j].
inline void apply_rope(Context&, float* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                       std::int64_t head_dim, const float* cos, const float* sin) {
  using simd::Batch;
  EPONA_CHECK(head_dim % 2 == 0, "apply_rope: head_dim must be even (interleaved pairs), got ", head_dim);
  const std::int64_t pairs = head_dim / 2;
  const Batch signs = simd::alternating_signs();
  simd::for_each_row(rows, heads * head_dim, [=](std::int64_t r) {
    const float* c = cos + r * pairs;
    const float* s = sin + r * pairs;
    // One chunk of kWidth channels (kWidth/2 pairs) at a time; its table serves every head.
    for (std::int64_t d0 = 0; d0 < head_dim; d0 += simd::kWidth) {
      const std::int64_t nd = std::min(simd::kWidth, head_dim - d0), np = nd / 2;
      const Batch cc = simd::dup_pairs(simd::load_partial(c + d0 / 2, np));
      const Batch ss = simd::dup_pairs(simd::load_partial(s + d0 / 2, np)) * signs;
      for (std::int64_t h = 0; h < heads; ++h) {
        float* p = x + r * row_stride + h * head_dim + d0;
        const Batch v = nd == simd::kWidth ? simd::load(p) : simd::load_partial(p, nd);
        const Batch y = v * cc + simd::swap_pairs(v) * ss;
        if (nd == simd::kWidth) simd::store(p, y);
        else simd::store_partial(p, y, nd);
      }
    }
  });
}

}  // namespace epona::cpu
