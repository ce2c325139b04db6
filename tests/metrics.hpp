// The metric every comparison in the tests states its tolerance in:
// rel_max = max|ours - ref| / max|ref|, infinite where either side holds a NaN or an infinity
// (so a poisoned, unwritten element always fails). The reference may be float32 (golden
// tensors, another backend) or float64 (the plain-loop references).
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "epona/core/tensor.hpp"

namespace epona::test {

template <class Ref>
double rel_max(const float* ours, const Ref* ref, std::int64_t n) {
  double diff = 0, scale = 0;
  for (std::int64_t i = 0; i < n; ++i) {
    const double a = ours[i], b = static_cast<double>(ref[i]);
    if (!std::isfinite(a) || !std::isfinite(b)) return INFINITY;
    diff = std::max(diff, std::abs(a - b));
    scale = std::max(scale, std::abs(b));
  }
  return scale > 0 ? diff / scale : diff;
}

inline void require_same_count(std::int64_t ours, std::int64_t ref) {
  REQUIRE_MESSAGE(ours == ref, "comparing ", ours, " values with ", ref);
}
inline double rel_max(const Tensor<float, Cpu>& ours, const Tensor<float, Cpu>& ref) {
  require_same_count(ours.numel(), ref.numel());
  return rel_max(ours.data(), ref.data(), ref.numel());
}
inline double rel_max(const Tensor<float, Cpu>& ours, const std::vector<double>& ref) {
  require_same_count(ours.numel(), static_cast<std::int64_t>(ref.size()));
  return rel_max(ours.data(), ref.data(), ours.numel());
}
inline double rel_max(const std::vector<float>& ours, const std::vector<double>& ref) {
  require_same_count(static_cast<std::int64_t>(ours.size()), static_cast<std::int64_t>(ref.size()));
  return rel_max(ours.data(), ref.data(), static_cast<std::int64_t>(ours.size()));
}

}  // namespace epona::test
