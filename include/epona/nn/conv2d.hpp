// epona/nn/conv2d.hpp — torch.nn.Conv2d (stride 1, "same" padding, groups, optional bias) with
// the activation of the enclosing ConvLayer fused into its epilogue, plus the parameter
// visiting every DC-AE layer uses: one `visit_params` per module lists its official names and
// shapes, and both weight binding (with a BindReport) and random initialisation walk it.
#pragma once

#include <cmath>
#include <cstdint>
#include <random>
#include <set>
#include <string>
#include <type_traits>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::nn {

// Fills parameter slots from a weight map; problems (missing, mis-shaped) go to the report.
// Vectors (norm affine, BatchNorm statistics, conv biases) stay float32 whatever T is.
class ParamBinder {
 public:
  ParamBinder(const io::TensorMap& map, io::BindReport& report) : map_(map), report_(report) {}

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = bind_param<B, T>(report_, name, shape);
  }
  // BatchNorm's `num_batches_tracked`: an int64 scalar that inference ignores. Absent is fine
  // (PyTorch tolerates that too); present with another type or shape is reported.
  void counter(const std::string& name) {
    if (!map_.contains(name)) return;
    counters_.insert(name);
    const io::RawTensor& r = map_.at(name);
    if (r.dtype != DType::I64 || r.numel() != 1)
      report_.problem("'" + name + "' should be an int64 scalar, is " + std::string(dtype_name(r.dtype)) + " " +
                      shape_str(r.shape));
  }
  // True for the counters visited so far (to exempt them from a strict report's "unexpected").
  bool is_counter(const std::string& name) const { return counters_.count(name) != 0; }

 private:
  const io::TensorMap& map_;
  io::BindReport& report_;
  std::set<std::string> counters_;
};

// Fills parameter slots with seeded random values of a sensible scale (benchmarks, tests):
// weights uniform with variance 1/fan_in, norm scales near 1, biases and means near 0,
// variances near 1.
class ParamRandomizer {
 public:
  explicit ParamRandomizer(std::uint64_t seed) : rng_(seed) {}

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    Tensor<T, Cpu> host(shape);
    const bool is_vector = shape.size() == 1;
    const auto ends_with = [&](const char* s) {
      const std::string suffix(s);
      return name.size() >= suffix.size() && name.compare(name.size() - suffix.size(), suffix.size(), suffix) == 0;
    };
    float center = 0.f, half_width;
    if (!is_vector) {
      const std::int64_t fan_in = shape_numel(shape) / shape[0];
      half_width = std::sqrt(3.0f / static_cast<float>(fan_in));
    } else if (ends_with("running_var") || ends_with("norm.weight")) {
      center = 1.f, half_width = 0.2f;
    } else {
      half_width = 0.1f;
    }
    std::uniform_real_distribution<float> u(center - half_width, center + half_width);
    for (std::int64_t i = 0; i < host.numel(); ++i) host.data()[i] = T(u(rng_));
    slot = BackendTraits<B>::upload(host);
  }
  void counter(const std::string&) {}

 private:
  std::mt19937_64 rng_;
};

// Mixin giving a module (with `template <class V> void visit_params(const std::string&, V&)`)
// the binding entry point of every epona layer.
template <class Derived>
struct Bindable {
  void bind(const io::TensorMap& map, const std::string& prefix, io::BindReport& report) {
    ParamBinder binder(map, report);
    static_cast<Derived&>(*this).visit_params(prefix, binder);
  }
  void randomize(std::uint64_t seed, const std::string& prefix = "") {
    ParamRandomizer r(seed);
    static_cast<Derived&>(*this).visit_params(prefix, r);
  }
};

// Conv2d(in, out, kernel, padding=kernel//2, groups, bias). Names: `weight` [out, in/groups, k, k],
// `bias` [out].
template <class B, class T>
struct Conv2d : Bindable<Conv2d<B, T>> {
  std::int64_t in_channels = 0, out_channels = 0, kernel = 1, groups = 1;
  bool has_bias = true;
  Tensor<T, B> weight;
  Tensor<float, B> bias;

  Conv2d() = default;
  Conv2d(std::int64_t in, std::int64_t out, std::int64_t k, std::int64_t g = 1, bool with_bias = true)
      : in_channels(in), out_channels(out), kernel(k), groups(g), has_bias(with_bias) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    v.param(prefix + "weight", weight, {out_channels, in_channels / groups, kernel, kernel});
    if (has_bias) v.param(prefix + "bias", bias, {out_channels});
  }

  // (N, out, H, W) for an input (N, in, H, W); anything else is an error naming the layer.
  Shape output_shape(const Tensor<float, B>& x) const {
    EPONA_CHECK(x.dim() == 4 && x.size(1) == in_channels, "Conv2d(", in_channels, "->", out_channels,
                "): input must be (N, ", in_channels, ", H, W), got ", shape_str(x.shape()));
    EPONA_CHECK(!weight.empty(), "Conv2d(", in_channels, "->", out_channels, "): weights not bound");
    return {x.size(0), out_channels, x.size(2), x.size(3)};
  }

  // y = act(conv(x) + bias); x (N, in, H, W), y (N, out, H, W) preallocated, not aliasing x.
  template <class Ctx>
  void forward_into(Ctx& ctx, const Tensor<float, B>& x, Tensor<float, B>& y, ConvAct act = ConvAct::None) const {
    check_shape(y, output_shape(x), "Conv2d output");
    const Conv2dShape s{x.size(0), in_channels, x.size(2), x.size(3), out_channels, kernel, groups};
    conv2d(ctx, x.data(), weight.data(), has_bias ? bias.data() : nullptr, y.data(), s, act);
  }
  template <class Ctx>
  Tensor<float, B> forward(Ctx& ctx, const Tensor<float, B>& x, ConvAct act = ConvAct::None) const {
    Tensor<float, B> y(output_shape(x));
    forward_into(ctx, x, y, act);
    return y;
  }
};

}  // namespace epona::nn
