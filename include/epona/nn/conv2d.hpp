// epona/nn/conv2d.hpp — torch.nn.Conv2d (stride 1, "same" padding, groups, optional bias) with
// the activation of the enclosing ConvLayer fused into its epilogue. Its parameters are visited
// like every layer's (nn/parameter.hpp); its weight in the backend's conv layout.
#pragma once

#include <cstdint>
#include <string>
#include <type_traits>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/feature_map.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::nn {

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
