// Plain float64 loops written straight from the DC-AE spec (docs/dcae.md §3-§6),
// shared by the tests/nn/dcae_*.cpp programs as the independent reference of each layer.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "epona/core/tensor.hpp"
#include "../ops/reference.hpp"
#include "reference_common.hpp"

namespace dcae_ref {

using namespace reference_common;  // Vec, i64, HostTensor, random_tensor, to_vec, rel_max

// The per-op references, written once in tests/ops/reference.hpp.
using ops_ref::average_shortcut;
using ops_ref::conv2d;
using ops_ref::duplicate_shortcut;
using ops_ref::relu;
using ops_ref::rms_norm_2d;
using ops_ref::shuffle;
using ops_ref::silu;
using ops_ref::unshuffle;

// LiteMLA attention core (§4.2.1 step 2-5) by its defining sums: per head, S(m,n) = Σ_j k[j,m] q[j,n]
// with q, k ReLU'd; out[i,n] = Σ_m v[i,m] S(m,n) / (Σ_m S(m,n) + eps).
inline Vec relu_linear_attention(const Vec& qkv, i64 N, i64 heads, i64 d, i64 HW, double eps) {
  Vec out(static_cast<std::size_t>(N * heads * d * HW));
  for (i64 n = 0; n < N; ++n)
    for (i64 a = 0; a < heads; ++a) {
      const double* base = qkv.data() + (n * heads * 3 + 3 * a) * d * HW;
      auto q = [&](i64 j, i64 p) { return relu(base[j * HW + p]); };
      auto k = [&](i64 j, i64 p) { return relu(base[(d + j) * HW + p]); };
      auto v = [&](i64 j, i64 p) { return base[(2 * d + j) * HW + p]; };
      for (i64 p = 0; p < HW; ++p) {
        Vec S(static_cast<std::size_t>(HW));
        double den = 0;
        for (i64 m = 0; m < HW; ++m) {
          double s = 0;
          for (i64 j = 0; j < d; ++j) s += k(j, m) * q(j, p);
          S[m] = s;
          den += s;
        }
        for (i64 i = 0; i < d; ++i) {
          double num = 0;
          for (i64 m = 0; m < HW; ++m) num += v(i, m) * S[m];
          out[((n * heads + a) * d + i) * HW + p] = num / (den + eps);
        }
      }
    }
  return out;
}

}  // namespace dcae_ref
