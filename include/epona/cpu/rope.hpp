// epona/cpu/rope.hpp — rotary position embedding with interleaved pairs (channels 2j, 2j+1
// form one complex number), as both the MST (2-D axial table) and the DiTs (3-axis table)
// apply it. The table is per token: cos/sin of shape (rows, head_dim/2), shared by all heads.
#pragma once

#include <cstdint>

#include "epona/cpu/context.hpp"

namespace epona::cpu {

// In place on `rows` tokens whose heads start at x + r * row_stride (heads side by side).
inline void apply_rope(Context&, float* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                       std::int64_t head_dim, const float* cos, const float* sin) {
  const std::int64_t pairs = head_dim / 2;
#pragma omp parallel for
  for (std::int64_t r = 0; r < rows; ++r)
    for (std::int64_t h = 0; h < heads; ++h) {
      float* p = x + r * row_stride + h * head_dim;
      const float* c = cos + r * pairs;
      const float* s = sin + r * pairs;
      for (std::int64_t j = 0; j < pairs; ++j) {
        const float a = p[2 * j], b = p[2 * j + 1];
        p[2 * j] = c[j] * a - s[j] * b;
        p[2 * j + 1] = s[j] * a + c[j] * b;
      }
    }
}

}  // namespace epona::cpu
