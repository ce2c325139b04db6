// The float64 reference of every backend op, written once, side by side: plain loops over
// std::vector<double>, straight from the specs (docs/world-model.md §3, §5-§7 for the world
// model's layers, docs/dcae.md §3-§6 for the DC-AE's) and the op contracts stated in
// include/epona/core/kernel_options.hpp and core/shapes.hpp. The op sweep (tests/ops/sweep.hpp)
// and the layer tests (tests/nn/world_reference.hpp, tests/nn/dcae_reference.hpp re-export these)
// compare against them. Row-major (rows, width) matrices unless said otherwise; maps are NCHW.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace ops_ref {

using Vec = std::vector<double>;
using i64 = std::int64_t;

// ---- activations ----
// GELU, exact: x·Φ(x).
inline double gelu_erf(double x) { return 0.5 * x * (1 + std::erf(x / std::sqrt(2.0))); }
// GELU, tanh approximation.
inline double gelu_tanh(double x) {
  return 0.5 * x * (1 + std::tanh(std::sqrt(2 / M_PI) * (x + 0.044715 * x * x * x)));
}
// SiLU: x·σ(x).
inline double silu(double x) { return x / (1 + std::exp(-x)); }
// ReLU: max(x, 0).
inline double relu(double v) { return v > 0 ? v : 0; }
// f applied to every element.
template <class F>
Vec map(Vec v, F f) {
  for (auto& x : v) x = f(x);
  return v;
}

// ---- products ----
// y[r, o] = b[o] + Σ_i x[r, i] · w[o, i]: nn.Linear over n rows (b may be null).
inline Vec linear(const Vec& x, i64 n, const Vec& w, const Vec* b, i64 in, i64 out) {
  Vec y(static_cast<std::size_t>(n * out));
  for (i64 r = 0; r < n; ++r)
    for (i64 o = 0; o < out; ++o) {
      double s = b ? (*b)[o] : 0.0;
      for (i64 i = 0; i < in; ++i) s += x[r * in + i] * w[o * in + i];
      y[r * out + o] = s;
    }
  return y;
}

// ---- elementwise ----
// x[r, :] += gate[:] ⊙ y[r, :] (gate null: plain residual add).
inline Vec add_gated(Vec x, const Vec& y, const Vec* gate, i64 rows, i64 n) {
  for (i64 r = 0; r < rows; ++r)
    for (i64 i = 0; i < n; ++i) x[r * n + i] += (gate ? (*gate)[i] : 1.0) * y[r * n + i];
  return x;
}
// y = a·v + x elementwise (axpy).
inline Vec axpy(Vec x, const Vec& v, double a) {
  for (std::size_t i = 0; i < x.size(); ++i) x[i] += a * v[i];
  return x;
}
// out[r, i] = value[r, i] · act(gate[r, i]) over rows of `width` (GLU gating).
template <class F>
Vec gated_act(const Vec& value, const Vec& gate, F act) {
  Vec out(value.size());
  for (std::size_t i = 0; i < value.size(); ++i) out[i] = value[i] * act(gate[i]);
  return out;
}
// Row softmax: y[r, i] = exp(x[r, i]) / Σ_j exp(x[r, j]).
inline Vec softmax_rows(const Vec& x, i64 rows, i64 n) {
  Vec y(x.size());
  for (i64 r = 0; r < rows; ++r) {
    double mx = -INFINITY, sum = 0;
    for (i64 i = 0; i < n; ++i) mx = std::max(mx, x[r * n + i]);
    for (i64 i = 0; i < n; ++i) sum += (y[r * n + i] = std::exp(x[r * n + i] - mx));
    for (i64 i = 0; i < n; ++i) y[r * n + i] /= sum;
  }
  return y;
}

// ---- norms ----
// LayerNorm over rows of `width`: (x − mean)/sqrt(var + eps) [· weight + bias when given].
inline Vec layer_norm(const Vec& x, i64 n, i64 width, double eps, const Vec* weight, const Vec* bias) {
  Vec y(x.size());
  for (i64 r = 0; r < n; ++r) {
    double mean = 0, var = 0;
    for (i64 i = 0; i < width; ++i) mean += x[r * width + i];
    mean /= width;
    for (i64 i = 0; i < width; ++i) var += (x[r * width + i] - mean) * (x[r * width + i] - mean);
    var /= width;
    for (i64 i = 0; i < width; ++i) {
      double v = (x[r * width + i] - mean) / std::sqrt(var + eps);
      if (weight) v *= (*weight)[i];
      if (bias) v += (*bias)[i];
      y[r * width + i] = v;
    }
  }
  return y;
}
// (1 + scale) ⊙ LN(x) + shift, LN without affine (adaLN modulation).
inline Vec modulate(const Vec& x, i64 n, i64 width, double eps, const double* shift, const double* scale) {
  Vec y = layer_norm(x, n, width, eps, nullptr, nullptr);
  for (i64 r = 0; r < n; ++r)
    for (i64 i = 0; i < width; ++i) y[r * width + i] = (1 + scale[i]) * y[r * width + i] + shift[i];
  return y;
}
// In place on the q (or k) part of packed rows: per head x·rsqrt(mean x² + eps)·scale.
inline void rms_heads(Vec& x, i64 n, i64 stride, i64 offset, i64 heads, i64 d, const Vec& scale, double eps) {
  for (i64 r = 0; r < n; ++r)
    for (i64 h = 0; h < heads; ++h) {
      double* p = &x[r * stride + offset + h * d];
      double ss = 0;
      for (i64 i = 0; i < d; ++i) ss += p[i] * p[i];
      const double rr = 1 / std::sqrt(ss / d + eps);
      for (i64 i = 0; i < d; ++i) p[i] = p[i] * rr * scale[i];
    }
}
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
// Eval BatchNorm2d: (x − mean[c]) / sqrt(var[c] + eps) · weight[c] + bias[c].
inline Vec batch_norm_2d(const Vec& x, i64 N, i64 C, i64 HW, const Vec& w, const Vec& b, const Vec& mean,
                         const Vec& var, double eps) {
  Vec y(x.size());
  for (i64 n = 0; n < N; ++n)
    for (i64 c = 0; c < C; ++c)
      for (i64 p = 0; p < HW; ++p)
        y[(n * C + c) * HW + p] = (x[(n * C + c) * HW + p] - mean[c]) / std::sqrt(var[c] + eps) * w[c] + b[c];
  return y;
}

// ---- rotary embedding ----
// Rotates pairs (2p, 2p+1) of every head by angle[r][p].
inline void rope(Vec& x, i64 n, i64 stride, i64 offset, i64 heads, i64 d, const std::vector<Vec>& angle) {
  for (i64 r = 0; r < n; ++r)
    for (i64 h = 0; h < heads; ++h)
      for (i64 p = 0; p < d / 2; ++p) {
        double* v = &x[r * stride + offset + h * d + 2 * p];
        const double c = std::cos(angle[r][p]), s = std::sin(angle[r][p]);
        const double a = v[0], b = v[1];
        v[0] = a * c - b * s;
        v[1] = a * s + b * c;
      }
}

// ---- attention ----
// Where a strided attention operand lives: element (s, i, h, c) at s·seq + i·row + h·d + c.
struct Strides {
  i64 seq = 0, row = 0;
};
// o[s, i, h, :] = Σ_j softmax_j(q·k / √d [+ mask[i, j]]) v[s, j, h, :], queries i < lq and keys
// j < lk (causal: j <= i); o dense (seqs, lq, heads, d). mask: optional (lq, lk) additive.
inline Vec attention(const Vec& q, Strides qs, const Vec& k, Strides ks, const Vec& v, Strides vs, i64 seqs, i64 heads,
                     i64 lq, i64 lk, i64 d, bool causal, const Vec* mask = nullptr) {
  Vec o(static_cast<std::size_t>(seqs * lq * heads * d), 0.0);
  for (i64 sq = 0; sq < seqs; ++sq)
    for (i64 h = 0; h < heads; ++h)
      for (i64 i = 0; i < lq; ++i) {
        const i64 nk = causal ? std::min(i + 1, lk) : lk;
        Vec s(static_cast<std::size_t>(nk));
        double mx = -INFINITY;
        for (i64 j = 0; j < nk; ++j) {
          double dot = 0;
          for (i64 c = 0; c < d; ++c)
            dot += q[sq * qs.seq + i * qs.row + h * d + c] * k[sq * ks.seq + j * ks.row + h * d + c];
          s[j] = dot / std::sqrt(double(d)) + (mask ? (*mask)[i * lk + j] : 0.0);
          mx = std::max(mx, s[j]);
        }
        double sum = 0;
        for (auto& e : s) sum += (e = std::exp(e - mx));
        double* out = &o[((sq * lq + i) * heads + h) * d];
        for (i64 j = 0; j < nk; ++j)
          for (i64 c = 0; c < d; ++c) out[c] += s[j] / sum * v[sq * vs.seq + j * vs.row + h * d + c];
      }
  return o;
}
// softmax(q kᵀ/√d) v over n tokens of packed rows (q at q_off, k at k_off, v at v_off, row
// stride `stride`), optionally causal; output (n, heads·d).
inline Vec attention(const Vec& x, i64 n, i64 stride, i64 q_off, i64 k_off, i64 v_off, i64 heads, i64 d, bool causal) {
  const Vec q(x.begin() + q_off, x.end()), k(x.begin() + k_off, x.end()), v(x.begin() + v_off, x.end());
  return attention(q, {0, stride}, k, {0, stride}, v, {0, stride}, 1, heads, n, n, d, causal);
}

// ---- the world model's fused token ops ----
// The MST's input tokens (core/kernel_options.hpp, FrameTokens): out (frames·items, actions +
// image_rows, width); item b's frame f is out frame f·items + b: its slot s < actions is
// actions[s·entries + b·entries/items + f] + time_emb[f], its row actions + l is
// LN(image[(b·frames + f)·image_rows + l])·weight + bias + time_emb[f].
inline Vec frame_tokens(const Vec& image, const Vec& actions, const Vec& time_emb, const Vec& weight, const Vec& bias,
                        i64 frames, i64 image_rows, i64 n_actions, i64 entries, i64 width, double eps, i64 items = 1) {
  const Vec ln = layer_norm(image, items * frames * image_rows, width, eps, &weight, &bias);
  const i64 tokens = n_actions + image_rows;
  Vec out(static_cast<std::size_t>(items * frames * tokens * width));
  for (i64 b = 0; b < items; ++b)
    for (i64 f = 0; f < frames; ++f)
      for (i64 t = 0; t < tokens; ++t)
        for (i64 c = 0; c < width; ++c)
          out[((f * items + b) * tokens + t) * width + c] =
              time_emb[f * width + c] +
              (t < n_actions ? actions[(t * entries + b * (entries / items) + f) * width + c]
                             : ln[((b * frames + f) * image_rows + t - n_actions) * width + c]);
  return out;
}

// ---- convolutions and shuffles (NCHW) ----
// LiteMLA attention core (dcae.md §4.2.1 steps 2-5) by its defining sums: per head, S(m,n) = Σ_j k[j,m] q[j,n]
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
// Calls f(i, j) for every element of a map (N, C, H, W): i its index there, j its index in the
// unshuffled map (N, C·r², H/r, W/r), where element [c, r·y + i', r·x + j'] goes to [c·r² + i'·r + j', y, x].
template <class F>
void unshuffle_pairs(i64 N, i64 C, i64 H, i64 W, i64 r, F f) {
  const i64 Ho = H / r, Wo = W / r, Co = C * r * r;
  for (i64 n = 0; n < N; ++n)
    for (i64 c = 0; c < C; ++c)
      for (i64 i = 0; i < r; ++i)
        for (i64 j = 0; j < r; ++j)
          for (i64 y = 0; y < Ho; ++y)
            for (i64 x = 0; x < Wo; ++x)
              f(((n * C + c) * H + r * y + i) * W + r * x + j, ((n * Co + c * r * r + i * r + j) * Ho + y) * Wo + x);
}
// Unshuffle (dcae.md §3.4): out[c·r² + i·r + j, y, x] = in[c, r·y + i, r·x + j].
inline Vec unshuffle(const Vec& in, i64 N, i64 C, i64 H, i64 W, i64 r) {
  Vec out(in.size());
  unshuffle_pairs(N, C, H, W, r, [&](i64 i, i64 j) { out[j] = in[i]; });
  return out;
}
// Shuffle (dcae.md §3.4), the inverse: out[c, r·y + i, r·x + j] = in[c·r² + i·r + j, y, x]; in has C·r² channels.
inline Vec shuffle(const Vec& in, i64 N, i64 Cin, i64 H, i64 W, i64 r) {
  Vec out(in.size());
  unshuffle_pairs(N, Cin / (r * r), H * r, W * r, r, [&](i64 i, i64 j) { out[i] = in[j]; });
  return out;
}
// Averaging shortcut (dcae.md §3.5): mean of g consecutive unshuffled channels.
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
// Duplicating shortcut (dcae.md §3.6): repeat-interleave channels rep times, then shuffle.
inline Vec duplicate_shortcut(const Vec& in, i64 N, i64 C, i64 H, i64 W, i64 r, i64 Co) {
  const i64 Cd = Co * r * r, rep = Cd / C, HW = H * W;
  Vec d(static_cast<std::size_t>(N * Cd * HW));
  for (i64 n = 0; n < N; ++n)
    for (i64 m = 0; m < Cd; ++m)
      for (i64 p = 0; p < HW; ++p) d[(n * Cd + m) * HW + p] = in[(n * C + m / rep) * HW + p];
  return r > 1 ? shuffle(d, N, Cd, H, W, r) : d;
}
// y[n, j, i] = x[n, i, j] for x (N, A, B).
inline Vec transpose_last2(const Vec& x, i64 N, i64 A, i64 B) {
  Vec y(x.size());
  for (i64 n = 0; n < N; ++n)
    for (i64 i = 0; i < A; ++i)
      for (i64 j = 0; j < B; ++j) y[(n * B + j) * A + i] = x[(n * A + i) * B + j];
  return y;
}

}  // namespace ops_ref
