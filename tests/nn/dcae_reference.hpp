// Plain float64 loops written straight from the DC-AE spec (/work/shared/spec/dcae.md §3-§6),
// shared by the tests/nn/dcae_*.cpp programs as the independent reference of each layer.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "epona/core/tensor.hpp"
#include "reference_common.hpp"

namespace dcae_ref {

using namespace reference_common;  // Vec, i64, HostTensor, random_tensor, to_vec, rel_max

// out[n,o,y,x] = b[o] + Σ_{i in group(o)} Σ_{dy,dx} W[o, i - first, dy, dx] · in[n, i, y+dy-k/2, x+dx-k/2].
inline Vec conv2d(const Vec& in, i64 N, i64 C, i64 H, i64 W, const Vec& w, const Vec* bias, i64 O, i64 k, i64 groups) {
  Vec out(static_cast<std::size_t>(N * O * H * W));
  const i64 cg = C / groups, og = O / groups, pad = k / 2;
  for (i64 n = 0; n < N; ++n)
    for (i64 o = 0; o < O; ++o)
      for (i64 y = 0; y < H; ++y)
        for (i64 x = 0; x < W; ++x) {
          double s = bias ? (*bias)[o] : 0.0;
          const i64 first = (o / og) * cg;
          for (i64 i = 0; i < cg; ++i)
            for (i64 dy = 0; dy < k; ++dy)
              for (i64 dx = 0; dx < k; ++dx) {
                const i64 ys = y + dy - pad, xs = x + dx - pad;
                if (ys < 0 || ys >= H || xs < 0 || xs >= W) continue;
                s += w[((o * cg + i) * k + dy) * k + dx] * in[((n * C + first + i) * H + ys) * W + xs];
              }
          out[((n * O + o) * H + y) * W + x] = s;
        }
  return out;
}

inline double silu(double v) { return v / (1.0 + std::exp(-v)); }
inline double relu(double v) { return v > 0 ? v : 0; }

// RMSNorm2d: per pixel over channels, then weight and bias.
inline Vec rms_norm_2d(const Vec& x, i64 N, i64 C, i64 HW, const Vec& w, const Vec& b, double eps) {
  Vec y(x.size());
  for (i64 n = 0; n < N; ++n)
    for (i64 p = 0; p < HW; ++p) {
      double ss = 0;
      for (i64 c = 0; c < C; ++c) ss += x[(n * C + c) * HW + p] * x[(n * C + c) * HW + p];
      const double r = 1.0 / std::sqrt(ss / double(C) + eps);
      for (i64 c = 0; c < C; ++c) y[(n * C + c) * HW + p] = x[(n * C + c) * HW + p] * r * w[c] + b[c];
    }
  return y;
}

// Unshuffle (§3.4): out[c·r² + i·r + j, y, x] = in[c, r·y + i, r·x + j].
inline Vec unshuffle(const Vec& in, i64 N, i64 C, i64 H, i64 W, i64 r) {
  Vec out(in.size());
  const i64 Ho = H / r, Wo = W / r, Co = C * r * r;
  for (i64 n = 0; n < N; ++n)
    for (i64 c = 0; c < C; ++c)
      for (i64 i = 0; i < r; ++i)
        for (i64 j = 0; j < r; ++j)
          for (i64 y = 0; y < Ho; ++y)
            for (i64 x = 0; x < Wo; ++x)
              out[((n * Co + c * r * r + i * r + j) * Ho + y) * Wo + x] = in[((n * C + c) * H + r * y + i) * W + r * x + j];
  return out;
}

// Shuffle (§3.4): out[c, r·y + i, r·x + j] = in[c·r² + i·r + j, y, x]; in has C·r² channels.
inline Vec shuffle(const Vec& in, i64 N, i64 Cin, i64 H, i64 W, i64 r) {
  Vec out(in.size());
  const i64 C = Cin / (r * r);
  for (i64 n = 0; n < N; ++n)
    for (i64 c = 0; c < C; ++c)
      for (i64 i = 0; i < r; ++i)
        for (i64 j = 0; j < r; ++j)
          for (i64 y = 0; y < H; ++y)
            for (i64 x = 0; x < W; ++x)
              out[((n * C + c) * H * r + r * y + i) * W * r + r * x + j] = in[((n * Cin + c * r * r + i * r + j) * H + y) * W + x];
  return out;
}

// Averaging shortcut (§3.5): mean of g consecutive unshuffled channels.
inline Vec average_shortcut(const Vec& in, i64 N, i64 C, i64 H, i64 W, i64 r, i64 Co) {
  const Vec u = r > 1 ? unshuffle(in, N, C, H, W, r) : in;
  const i64 Cu = C * r * r, g = Cu / Co, HW = H * W / (r * r);
  Vec out(static_cast<std::size_t>(N * Co * HW), 0.0);
  for (i64 n = 0; n < N; ++n)
    for (i64 k = 0; k < Co; ++k)
      for (i64 p = 0; p < HW; ++p) {
        double s = 0;
        for (i64 t = 0; t < g; ++t) s += u[(n * Cu + k * g + t) * HW + p];
        out[(n * Co + k) * HW + p] = s / double(g);
      }
  return out;
}

// Duplicating shortcut (§3.6): repeat-interleave channels rep times, then shuffle.
inline Vec duplicate_shortcut(const Vec& in, i64 N, i64 C, i64 H, i64 W, i64 r, i64 Co) {
  const i64 Cd = Co * r * r, rep = Cd / C, HW = H * W;
  Vec d(static_cast<std::size_t>(N * Cd * HW));
  for (i64 n = 0; n < N; ++n)
    for (i64 m = 0; m < Cd; ++m)
      for (i64 p = 0; p < HW; ++p) d[(n * Cd + m) * HW + p] = in[(n * C + m / rep) * HW + p];
  return r > 1 ? shuffle(d, N, Cd, H, W, r) : d;
}

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
