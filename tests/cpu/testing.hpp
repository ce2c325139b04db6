// Shared helpers of the CPU kernel tests: seeded random data and the error measure every
// test states its tolerance in (max |got − ref| / max |ref|, the reference in float64).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "../metrics.hpp"  // rel_max, the error measure

namespace epona::test {

inline std::vector<float> random_floats(std::size_t n, std::uint32_t seed, float lo = -1.f, float hi = 1.f) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> dist(lo, hi);
  std::vector<float> v(n);
  for (auto& x : v) x = dist(gen);
  return v;
}

// Sizes around the SIMD widths (4, 8, 16 floats) and their tails.
inline const std::vector<std::int64_t>& odd_sizes() {
  static const std::vector<std::int64_t> s{1, 3, 7, 8, 15, 16, 17, 31, 33, 100, 257, 2051};
  return s;
}

}  // namespace epona::test
