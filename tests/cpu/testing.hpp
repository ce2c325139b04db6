// Shared helpers of the CPU kernel tests: seeded random data and the error measure every
// test states its tolerance in (max |got − ref| / max |ref|, the reference in float64).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

namespace epona::test {

inline std::vector<float> random_floats(std::size_t n, std::uint32_t seed, float lo = -1.f, float hi = 1.f) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> dist(lo, hi);
  std::vector<float> v(n);
  for (auto& x : v) x = dist(gen);
  return v;
}

// max |got - ref| / max |ref| over n elements (0 when both are all zero).
inline double max_rel_error(const float* got, const double* ref, std::size_t n) {
  double err = 0, scale = 0;
  for (std::size_t i = 0; i < n; ++i) {
    err = std::max(err, std::abs(static_cast<double>(got[i]) - ref[i]));
    scale = std::max(scale, std::abs(ref[i]));
  }
  return scale > 0 ? err / scale : err;
}
inline double max_rel_error(const std::vector<float>& got, const std::vector<double>& ref) {
  return max_rel_error(got.data(), ref.data(), std::min(got.size(), ref.size()));
}

// Sizes around the SIMD widths (4, 8, 16 floats) and their tails.
inline const std::vector<std::int64_t>& odd_sizes() {
  static const std::vector<std::int64_t> s{1, 3, 7, 8, 15, 16, 17, 31, 33, 100, 257, 2051};
  return s;
}

}  // namespace epona::test
