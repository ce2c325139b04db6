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
#include "epona/nn/feature_map.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::nn {

// A conv weight [out, in/groups, k, k] (PyTorch) in backend B's layout: unchanged for NCHW
// backends, [out, k, k, in/groups] for channels-last ones (the GEMM's K = (ky, kx, c) order).
template <class B, class T>
Tensor<T, Cpu> conv_weight_layout(Tensor<T, Cpu> w) {
  if constexpr (!channels_last_maps<B>) {
    return w;
  } else {
    EPONA_CHECK(w.dim() == 4 && w.size(2) == w.size(3), "conv weight must be [out, in, k, k], got ", shape_str(w.shape()));
    const std::int64_t O = w.size(0), C = w.size(1), k = w.size(2);
    Tensor<T, Cpu> out({O, k, k, C});
    for (std::int64_t o = 0; o < O; ++o)
      for (std::int64_t c = 0; c < C; ++c)
        for (std::int64_t t = 0; t < k * k; ++t) out.data()[(o * k * k + t) * C + c] = w.data()[(o * C + c) * k * k + t];
    return out;
  }
}

// Fills parameter slots from a weight map; problems (missing, mis-shaped) go to the report.
// Vectors (norm affine, BatchNorm statistics, conv biases) stay float32 whatever T is.
class ParamBinder {
 public:
  ParamBinder(const io::TensorMap& map, io::BindReport& report) : map_(map), report_(report) {}

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = bind_param<B, T>(report_, name, shape);
  }
  // A conv weight [out, in/groups, k, k], stored in backend B's conv layout (conv_weight_layout).
  template <class T, class B>
  void conv_weight(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    const io::RawTensor* raw = report_.take(name, shape);
    slot = raw ? BackendTraits<B>::upload(conv_weight_layout<B>(io::to_tensor<T>(*raw))) : Tensor<T, B>();
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
// variances near 1. Values depend only on the seed and the visiting order (not on the backend).
class ParamRandomizer {
 public:
  explicit ParamRandomizer(std::uint64_t seed) : rng_(seed) {}

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = BackendTraits<B>::upload(values<T>(name, shape));
  }
  template <class T, class B>
  void conv_weight(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = BackendTraits<B>::upload(conv_weight_layout<B>(values<T>(name, shape)));
  }
  void counter(const std::string&) {}

 private:
  template <class T>
  Tensor<T, Cpu> values(const std::string& name, const Shape& shape) {
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
    // 24 random bits per value -> uniform in [center - half_width, center + half_width): one
    // generator step per value (the real model has 324 M of them).
    constexpr float unit = 1.0f / 16777216.0f;
    for (std::int64_t i = 0; i < host.numel(); ++i) {
      const float u = static_cast<float>(rng_() >> 40) * unit;
      host.data()[i] = T(center + half_width * (2.0f * u - 1.0f));
    }
    return host;
  }

  std::mt19937_64 rng_;
};

// Routes a conv weight to the visitor's `conv_weight` when it has one (binding, randomising),
// else to its plain `param` (visitors that only read names and shapes).
template <class V, class T, class B>
void visit_conv_weight(V& v, const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
  if constexpr (requires { v.conv_weight(name, slot, shape); })
    v.conv_weight(name, slot, shape);
  else
    v.param(name, slot, shape);
}

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

// Conv2d(in, out, kernel, padding=kernel//2, groups, bias). Names: `weight` [out, in/groups, k, k]
// (stored as [out, k, k, in/groups] on channels-last backends), `bias` [out].
// Feature maps are Tensor<activation_t<B, T>, B> in B's layout (nn/feature_map.hpp).
template <class B, class T>
struct Conv2d : Bindable<Conv2d<B, T>> {
  using Act = activation_t<B, T>;
  using Map = Tensor<Act, B>;

  std::int64_t in_channels = 0, out_channels = 0, kernel = 1, groups = 1;
  bool has_bias = true;
  Tensor<T, B> weight;
  Tensor<Act, B> bias;  // float on the CPU; the activation type on CUDA (as autocast casts it)

  Conv2d() = default;
  Conv2d(std::int64_t in, std::int64_t out, std::int64_t k, std::int64_t g = 1, bool with_bias = true)
      : in_channels(in), out_channels(out), kernel(k), groups(g), has_bias(with_bias) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    visit_conv_weight(v, prefix + "weight", weight, {out_channels, in_channels / groups, kernel, kernel});
    if (has_bias) v.param(prefix + "bias", bias, {out_channels});
  }

  // Extents of the output for input x; a wrong input is an error naming the layer.
  MapDims output_dims(const Map& x) const {
    const std::string what = "Conv2d(" + std::to_string(in_channels) + "->" + std::to_string(out_channels) + ")";
    MapDims d = map_dims(x, what, in_channels);
    EPONA_CHECK(!weight.empty(), what, ": weights not bound");
    d.channels = out_channels;
    return d;
  }
  Shape output_shape(const Map& x) const { return map_shape<B>(output_dims(x)); }

  // y = act(conv(x) + bias); y preallocated with output_shape(x), not aliasing x.
  template <class Ctx>
  void forward_into(Ctx& ctx, const Map& x, Map& y, ConvAct act = ConvAct::None) const {
    const MapDims d = output_dims(x);
    check_shape(y, map_shape<B>(d), "Conv2d output");
    const Conv2dShape s{d.batch, in_channels, d.height, d.width, out_channels, kernel, groups};
    conv2d(ctx, x.data(), weight.data(), has_bias ? bias.data() : nullptr, y.data(), s, act);
  }
  template <class Ctx>
  Map forward(Ctx& ctx, const Map& x, ConvAct act = ConvAct::None) const {
    Map y = new_map<Act, B>(ctx, output_dims(x));
    forward_into(ctx, x, y, act);
    return y;
  }
};

}  // namespace epona::nn
