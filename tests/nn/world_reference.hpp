// Plain float64 loops written straight from the world-model spec (world-model.md §3, §5-§7),
// shared by the tests/nn world-model programs as the independent reference of each layer and
// block, plus random weights under the official names (a TensorMap the layers bind from).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/parameter.hpp"
#include "reference_common.hpp"

namespace world_ref {

using namespace reference_common;  // Vec, i64, HostTensor, random_tensor, to_vec, rel_max

// Random float32 parameters under official names, readable back as float64.
class RandomWeights {
 public:
  // bf16_storage: tensors are stored as bfloat16 (as the released checkpoint most likely is);
  // the float64 copies hold exactly the stored values.
  explicit RandomWeights(std::uint64_t seed, bool bf16_storage = false)
      : rng_(seed), map_("random weights"), bf16_(bf16_storage) {}

  // Uniform in [offset - scale, offset + scale].
  void add(const std::string& name, const epona::Shape& shape, double scale, double offset = 0) {
    auto data = std::make_shared<std::vector<float>>(static_cast<std::size_t>(epona::shape_numel(shape)));
    std::uniform_real_distribution<double> u(-scale, scale);
    for (auto& v : *data) v = static_cast<float>(offset + u(rng_));
    epona::io::RawTensor r;
    r.shape = shape;
    if (bf16_) {
      auto half = std::make_shared<std::vector<epona::bf16>>();
      for (auto& v : *data) {
        half->push_back(epona::bf16(v));
        v = float(half->back());
      }
      r.dtype = epona::DType::BF16;
      r.bytes = std::span<const std::byte>(reinterpret_cast<const std::byte*>(half->data()), half->size() * 2);
      map_.keep_alive(half);
    } else {
      r.dtype = epona::DType::F32;
      r.bytes = std::span<const std::byte>(reinterpret_cast<const std::byte*>(data->data()), data->size() * 4);
      map_.keep_alive(data);
    }
    map_.add(name, r);
    values_[name] = Vec(data->begin(), data->end());
  }
  // Linear(in -> out): weight scaled 1/sqrt(in) so activations stay O(1).
  void linear(const std::string& prefix, i64 in, i64 out, bool bias) {
    add(prefix + "weight", {out, in}, 1.0 / std::sqrt(double(in)));
    if (bias) add(prefix + "bias", {out}, 0.1);
  }
  void layer_norm(const std::string& prefix, i64 n) {
    add(prefix + "weight", {n}, 0.2, 1.0);
    add(prefix + "bias", {n}, 0.2);
  }
  // Every parameter of a layer's tree (its `parameters()`): matrices as `linear`'s weights,
  // vectors named `weight` or `scale` (norm scales) near 1, others (biases) near 0. The names
  // come from the layer; the reference reads them back by the names it expects.
  void add_all(const epona::nn::ParamList& list) {
    for (const auto& e : list.entries()) {
      const bool scale = e.name.ends_with("weight") || e.name.ends_with("scale");
      if (e.shape.size() != 1)
        add(e.name, e.shape, 1.0 / std::sqrt(double(epona::shape_numel(e.shape) / e.shape[0])));
      else
        add(e.name, e.shape, 0.2, scale ? 1.0 : 0.0);
    }
  }
  const Vec& operator[](const std::string& name) const { return values_.at(name); }
  const epona::io::TensorMap& map() const { return map_; }

 private:
  std::mt19937_64 rng_;
  epona::io::TensorMap map_;
  bool bf16_ = false;
  std::map<std::string, Vec> values_;
};

// ---- layers (rows of a row-major (n, width) matrix) ----
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
inline Vec linear(const RandomWeights& w, const std::string& p, const Vec& x, i64 n, i64 in, i64 out, bool bias) {
  return linear(x, n, w[p + "weight"], bias ? &w[p + "bias"] : nullptr, in, out);
}
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
      if (weight) v = v * (*weight)[i] + (*bias)[i];
      y[r * width + i] = v;
    }
  }
  return y;
}
inline double gelu_erf(double x) { return 0.5 * x * (1 + std::erf(x / std::sqrt(2.0))); }
inline double gelu_tanh(double x) {
  return 0.5 * x * (1 + std::tanh(std::sqrt(2 / M_PI) * (x + 0.044715 * x * x * x)));
}
inline double silu(double x) { return x / (1 + std::exp(-x)); }
template <class F>
Vec map(Vec v, F f) {
  for (auto& x : v) x = f(x);
  return v;
}
// (1 + scale) ⊙ LN(x) + shift, LN without affine.
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
// softmax(q kᵀ/√d) v over n tokens of packed rows (q at q_off, k at k_off, v at v_off, row
// stride `stride`), optionally causal; output (n, heads·d).
inline Vec attention(const Vec& x, i64 n, i64 stride, i64 q_off, i64 k_off, i64 v_off, i64 heads, i64 d, bool causal) {
  Vec o(static_cast<std::size_t>(n * heads * d), 0.0);
  for (i64 h = 0; h < heads; ++h)
    for (i64 i = 0; i < n; ++i) {
      const i64 nk = causal ? i + 1 : n;
      Vec s(static_cast<std::size_t>(nk));
      double mx = -INFINITY;
      for (i64 j = 0; j < nk; ++j) {
        double dot = 0;
        for (i64 c = 0; c < d; ++c) dot += x[i * stride + q_off + h * d + c] * x[j * stride + k_off + h * d + c];
        s[j] = dot / std::sqrt(double(d));
        mx = std::max(mx, s[j]);
      }
      double sum = 0;
      for (auto& v : s) sum += (v = std::exp(v - mx));
      for (i64 j = 0; j < nk; ++j)
        for (i64 c = 0; c < d; ++c) o[i * heads * d + h * d + c] += s[j] / sum * x[j * stride + v_off + h * d + c];
    }
  return o;
}

// ---- embeddings ----
inline Vec fourier(const Vec& coords, i64 dim, double max_period) {
  const i64 half = dim / 2;
  Vec out(coords.size() * dim);
  for (std::size_t i = 0; i < coords.size(); ++i)
    for (i64 k = 0; k < half; ++k) {
      const double a = coords[i] * std::pow(max_period, double(k) / half);
      out[i * dim + k] = std::sin(a);
      out[i * dim + half + k] = std::cos(a);
    }
  return out;
}
inline Vec timestep(double t, i64 dim, double max_period, double factor) {
  const i64 half = dim / 2;
  Vec out(static_cast<std::size_t>(dim), 0.0);
  for (i64 k = 0; k < half; ++k) {
    const double a = factor * t * std::exp(-std::log(max_period) * k / half);
    out[k] = std::cos(a);
    out[half + k] = std::sin(a);
  }
  return out;
}

}  // namespace world_ref
