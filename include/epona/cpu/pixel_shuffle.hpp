// epona/cpu/pixel_shuffle.hpp — NCHW data movement of the DC-AE: pixel (un)shuffle (torch's
// F.pixel_unshuffle / F.pixel_shuffle channel order), the parameter-free residual shortcuts
// (channel averaging after unshuffle, channel repeat-interleave before shuffle) fused into
// one pass each, and the (n, a, b) -> (n, b, a) transpose between NCHW and channels-last tokens.
#pragma once

#include <algorithm>
#include <cstdint>

#include "epona/core/shapes.hpp"
#include "epona/cpu/context.hpp"

namespace epona::cpu {

namespace shuffle_detail {
inline void check(const ShuffleShape& s, const char* what) {
  EPONA_CHECK(s.batch >= 0 && s.channels > 0 && s.height > 0 && s.width > 0 && s.factor >= 1, what,
              ": bad geometry N=", s.batch, " C=", s.channels, " H=", s.height, " W=", s.width, " r=", s.factor);
}

// Writes or accumulates (y += v) element by element; `value(n, c, y, x)` gives output (n, c, y, x).
template <class Value>
void fill_output(float* out, std::int64_t N, std::int64_t C, std::int64_t H, std::int64_t W, bool accumulate,
                 Value value) {
#pragma omp parallel for collapse(2)
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t c = 0; c < C; ++c) {
      float* d = out + (n * C + c) * H * W;
      for (std::int64_t y = 0; y < H; ++y)
        for (std::int64_t x = 0; x < W; ++x) {
          const float v = value(n, c, y, x);
          d[y * W + x] = accumulate ? d[y * W + x] + v : v;
        }
    }
}
}  // namespace shuffle_detail

// Unshuffled channel cu of pixel (y, x) reads input channel cu / r², row r·y + (cu % r²) / r,
// column r·x + cu % r (input channel slowest, then row offset, then column offset).
// out (N, C·r², H/r, W/r) (+)= unshuffle(x); with channels_out < C·r², each output channel is
// instead the mean of g = C·r²/channels_out consecutive unshuffled channels (the averaging
// shortcut; channels_out = C·r² is the plain unshuffle).
inline void pixel_unshuffle_average(Context&, const float* x, float* out, const ShuffleShape& s,
                                    std::int64_t channels_out, bool accumulate = false) {
  shuffle_detail::check(s, "pixel_unshuffle");
  const std::int64_t r = s.factor, r2 = r * r, H = s.height, W = s.width;
  EPONA_CHECK(H % r == 0 && W % r == 0, "pixel_unshuffle: ", H, "x", W, " is not divisible by factor ", r);
  EPONA_CHECK(channels_out > 0 && (s.channels * r2) % channels_out == 0, "channel averaging: ", s.channels,
              "·", r2, " unshuffled channels do not split into ", channels_out, " groups");
  const std::int64_t g = s.channels * r2 / channels_out, C = s.channels;
  shuffle_detail::fill_output(out, s.batch, channels_out, H / r, W / r, accumulate,
                              [=](std::int64_t n, std::int64_t k, std::int64_t y, std::int64_t xo) {
                                float sum = 0.f;
                                for (std::int64_t t = 0; t < g; ++t) {
                                  const std::int64_t cu = k * g + t, sub = cu % r2;
                                  sum += x[((n * C + cu / r2) * H + r * y + sub / r) * W + r * xo + sub % r];
                                }
                                return g == 1 ? sum : sum / static_cast<float>(g);
                              });
}

// Shuffle, the exact inverse: out[c, r·y + i, r·x + j] = d[c·r² + i·r + j, y, x], where d repeats
// each of the C input channels rep = channels_out·r²/C times consecutively (repeat-interleave;
// rep = 1 is the plain shuffle, the duplicating shortcut otherwise). out (N, channels_out, H·r, W·r).
inline void pixel_shuffle_duplicate(Context&, const float* x, float* out, const ShuffleShape& s,
                                    std::int64_t channels_out, bool accumulate = false) {
  shuffle_detail::check(s, "pixel_shuffle");
  const std::int64_t r = s.factor, r2 = r * r, H = s.height, W = s.width, C = s.channels;
  EPONA_CHECK(channels_out > 0 && (channels_out * r2) % C == 0, "channel duplication: ", channels_out, "·", r2,
              " shuffled channels are not a multiple of the ", C, " input channels");
  const std::int64_t rep = channels_out * r2 / C;
  shuffle_detail::fill_output(out, s.batch, channels_out, H * r, W * r, accumulate,
                              [=](std::int64_t n, std::int64_t c, std::int64_t yo, std::int64_t xo) {
                                const std::int64_t m = c * r2 + (yo % r) * r + xo % r;
                                return x[((n * C + m / rep) * H + yo / r) * W + xo / r];
                              });
}

// y[n, j, i] = x[n, i, j] for x (N, A, B): NCHW (N, C, HW) <-> channels-last tokens (N, HW, C).
inline void transpose_last2(Context&, const float* x, float* y, std::int64_t N, std::int64_t A, std::int64_t B) {
  constexpr std::int64_t tile = 32;
#pragma omp parallel for collapse(2)
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t i0 = 0; i0 < A; i0 += tile)
      for (std::int64_t j0 = 0; j0 < B; j0 += tile)
        for (std::int64_t i = i0; i < std::min(A, i0 + tile); ++i)
          for (std::int64_t j = j0; j < std::min(B, j0 + tile); ++j) y[(n * B + j) * A + i] = x[(n * A + i) * B + j];
}

}  // namespace epona::cpu
