// What the float64 reference headers (dcae_reference.hpp, world_reference.hpp) share: host
// tensors of uniform random values, their float64 copies, and the comparison metric
// (tests/metrics.hpp).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "../metrics.hpp"
#include "../ops/reference.hpp"
#include "epona/core/tensor.hpp"

namespace reference_common {

using ops_ref::Vec;
using ops_ref::i64;
using HostTensor = epona::Tensor<float, epona::Cpu>;

inline HostTensor random_tensor(const epona::Shape& shape, std::uint64_t seed, float lo = -1.f, float hi = 1.f) {
  HostTensor t(shape);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(lo, hi);
  for (i64 i = 0; i < t.numel(); ++i) t.data()[i] = u(rng);
  return t;
}

inline Vec to_vec(const HostTensor& t) { return Vec(t.data(), t.data() + t.numel()); }

using epona::test::rel_max;  // tests/metrics.hpp: against a float64 reference too

}  // namespace reference_common
