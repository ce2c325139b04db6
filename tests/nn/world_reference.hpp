// Plain float64 loops written straight from the world-model spec (world-model.md §3, §5-§7),
// shared by the tests/nn world-model programs as the independent reference of each layer and
// block (the per-op loops live in tests/ops/reference.hpp, re-exported here), plus random weights under the official names (a TensorMap the layers bind from).
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
#include "../ops/reference.hpp"
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

// ---- layers: the float64 references of the ops, in tests/ops/reference.hpp ----
using ops_ref::attention;
using ops_ref::gelu_erf;
using ops_ref::gelu_tanh;
using ops_ref::layer_norm;
using ops_ref::linear;
using ops_ref::map;
using ops_ref::modulate;
using ops_ref::rms_heads;
using ops_ref::rope;
using ops_ref::silu;
inline Vec linear(const RandomWeights& w, const std::string& p, const Vec& x, i64 n, i64 in, i64 out, bool bias) {
  return linear(x, n, w[p + "weight"], bias ? &w[p + "bias"] : nullptr, in, out);
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
