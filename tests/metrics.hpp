// The metric every comparison in the tests states its tolerance in:
// rel_max = max|ours - ref| / max|ref|, infinite where either side holds a NaN or an infinity
// (so a poisoned, unwritten element always fails).
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "epona/core/tensor.hpp"

namespace epona::test {

inline double rel_max(const Tensor<float, Cpu>& ours, const Tensor<float, Cpu>& ref) {
  REQUIRE_MESSAGE(ours.numel() == ref.numel(), "comparing ", ours.numel(), " values with ", ref.numel());
  double diff = 0, scale = 0;
  for (std::int64_t i = 0; i < ref.numel(); ++i) {
    const double a = ours.data()[i], b = ref.data()[i];
    if (!std::isfinite(a) || !std::isfinite(b)) return INFINITY;
    diff = std::max(diff, std::abs(a - b));
    scale = std::max(scale, std::abs(b));
  }
  return scale > 0 ? diff / scale : diff;
}

}  // namespace epona::test
