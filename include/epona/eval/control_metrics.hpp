// epona/eval/control_metrics.hpp — does the world model obey the action it is given? Two frames
// generated from the same window and noise, one under "turn left" and one under "turn right", must
// show the road shifted the matching way. The shift between them is the integer column offset
// that best aligns their lower parts (below the horizon: road, markings, kerbs), found by
// exhaustive search on grey levels (mean absolute difference). No learned features, no
// calibration: the sign is what is scored, the size is reported.
//
// Sign convention: shift s > 0 means a's content lies s columns to the RIGHT of b's
// (a(y, x) ~ b(y, x - s)). A left turn (yaw > 0, Epona's left-positive convention) rotates the
// camera left, so the scene moves right in the image: shift(left frame, right frame) > 0.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/io/image.hpp"

namespace epona::eval {

struct ShiftSearch {
  std::int64_t row_begin = -1, row_end = -1;  // rows compared, [begin, end); -1 -1: the lower half
  std::int64_t max_shift = -1;                // candidates -max..max; -1: width / 4
};

struct ShiftEstimate {
  std::int64_t shift = 0;    // the best candidate (sign convention above)
  double mad = 0;            // its mean absolute grey difference (0..255)
  double mad_at_zero = 0;    // the same at shift 0 (how much the frames differ unaligned)
};

namespace shift_detail {

// (r + g + b) / 3 per pixel of rows [r0, r1), row-major.
inline std::vector<float> grey_rows(const io::Image& img, std::int64_t r0, std::int64_t r1) {
  std::vector<float> g(static_cast<std::size_t>((r1 - r0) * img.width));
  for (std::int64_t y = r0; y < r1; ++y)
    for (std::int64_t x = 0; x < img.width; ++x)
      g[static_cast<std::size_t>((y - r0) * img.width + x)] =
          (float(img.at(y, x, 0)) + float(img.at(y, x, 1)) + float(img.at(y, x, 2))) / 3.0f;
  return g;
}

}  // namespace shift_detail

// The horizontal shift of `a` relative to `b`. Every candidate compares the same pixels of a (its
// central columns [max, W - max), which stay inside b for every candidate), so candidates differ
// only in the alignment, not in how much border they see.
inline ShiftEstimate horizontal_shift(const io::Image& a, const io::Image& b, const ShiftSearch& s = {}) {
  EPONA_CHECK(a.height == b.height && a.width == b.width && !a.rgb.empty() &&
                  a.rgb.size() == static_cast<std::size_t>(a.height * a.width * 3) && b.rgb.size() == a.rgb.size(),
              "horizontal_shift: the images differ in size (", a.height, "x", a.width, " vs ", b.height, "x", b.width, ")");
  const std::int64_t H = a.height, W = a.width;
  const std::int64_t r0 = s.row_begin < 0 ? H / 2 : s.row_begin, r1 = s.row_end < 0 ? H : s.row_end;
  const std::int64_t M = s.max_shift < 0 ? W / 4 : s.max_shift;
  EPONA_CHECK(0 <= r0 && r0 < r1 && r1 <= H, "horizontal_shift: rows [", r0, ", ", r1, ") outside the image's ", H);
  EPONA_CHECK(2 * M < W, "horizontal_shift: a search over +-", M, " columns leaves nothing of a ", W, "-wide image");
  const std::vector<float> ga = shift_detail::grey_rows(a, r0, r1), gb = shift_detail::grey_rows(b, r0, r1);
  const double count = double(r1 - r0) * double(W - 2 * M);
  const auto mad = [&](std::int64_t shift) {
    double sum = 0;
    for (std::int64_t y = 0; y < r1 - r0; ++y) {
      const float* pa = ga.data() + y * W;
      const float* pb = gb.data() + y * W;
      for (std::int64_t x = M; x < W - M; ++x) sum += std::abs(double(pa[x]) - double(pb[x - shift]));
    }
    return sum / count;
  };
  ShiftEstimate e;
  e.mad = std::numeric_limits<double>::infinity();
  // Ties go to the smallest |shift| (then the negative one): an uninformative pair reads 0, no turn.
  for (std::int64_t d = 0; d <= M; ++d)
    for (const std::int64_t shift : {-d, d}) {
      const double v = mad(shift);
      if (v < e.mad) e.mad = v, e.shift = shift;
      if (d == 0) break;
    }
  e.mad_at_zero = mad(0);
  return e;
}

}  // namespace epona::eval
