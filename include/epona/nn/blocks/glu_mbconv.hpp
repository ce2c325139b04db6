// epona/nn/blocks/glu_mbconv.hpp — GLUMBConv of EfficientViT (the DC-AE's "local module"): 1x1 expansion
// C -> 8C with bias and activation, depthwise 3x3 with bias (no activation), value · act(gate)
// over the two halves, 1x1 projection 4C -> C without bias, then its norm. Returns the branch.
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/nn/conv2d.hpp"
#include "epona/nn/feature_map.hpp"
#include "epona/nn/norm2d.hpp"

namespace epona::nn {

// Names (under the branch prefix): `inverted_conv.conv.{weight [8C, C, 1, 1], bias}`,
// `depth_conv.conv.{weight [8C, 1, 3, 3], bias}`, `point_conv.conv.weight` [C, 4C, 1, 1],
// `point_conv.norm.*`. `act` follows the expansion and gates the value half (SiLU in every
// DC-AE configuration).
template <class B, class T>
struct GLUMBConv : Bindable<GLUMBConv<B, T>> {
  std::int64_t channels = 0, hidden = 0;  // hidden = expand_ratio · C (4C)
  ConvAct act = ConvAct::Silu;
  Conv2d<B, T> inverted_conv, depth_conv, point_conv;
  Norm2d<B, T> point_norm;

  GLUMBConv() = default;
  GLUMBConv(std::int64_t c, Norm2dKind norm, ConvAct activation, std::int64_t expand = 4)
      : channels(c), hidden(expand * c), act(activation), inverted_conv(c, 2 * expand * c, 1),
        depth_conv(2 * expand * c, 2 * expand * c, 3, 2 * expand * c), point_conv(expand * c, c, 1, 1, false),
        point_norm(norm, c) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    inverted_conv.visit_params(prefix + "inverted_conv.conv.", v);
    depth_conv.visit_params(prefix + "depth_conv.conv.", v);
    point_conv.visit_params(prefix + "point_conv.conv.", v);
    point_norm.visit_params(prefix + "point_conv.norm.", v);
  }

  using Act = activation_t<B, T>;
  using Map = Tensor<Act, B>;

  // x (a map of C channels) -> the branch output, same extents (the EfficientViT block adds x).
  template <class Ctx>
  Map forward(Ctx& ctx, const Map& x) const {
    Map y = expand_gate_project(ctx, x);
    point_norm.forward_inplace(ctx, y);
    return y;
  }
  // x += forward(x).
  template <class Ctx>
  void add_to(Ctx& ctx, Map& x) const {
    Map y = expand_gate_project(ctx, x);
    point_norm.add_to(ctx, y, x);
  }

 private:
  template <class Ctx>
  Map expand_gate_project(Ctx& ctx, const Map& x) const {
    MapDims d = map_dims(x, "GLUMBConv(" + std::to_string(channels) + ")", channels);
    Map expanded = inverted_conv.forward(ctx, x, act);  // 8C channels
    Map mixed = depth_conv.forward(ctx, expanded);      // 8C channels
    d.channels = hidden;
    Map gated = new_map<Act, B>(ctx, d);                // 4C channels
    // value = channels [0, 4C), gate = channels [4C, 8C) of `mixed`
    const MapDims dm{d.batch, 2 * hidden, d.height, d.width};
    const ChannelBlock value = channel_block<B>(dm, 0, hidden), gate = channel_block<B>(dm, hidden, hidden);
    const ChannelBlock out = channel_block<B>(d, 0, hidden);
    gated_act(ctx, mixed.data() + value.offset, mixed.data() + gate.offset, gated.data(), value.rows, value.width,
              value.stride, out.stride, act);
    return point_conv.forward(ctx, gated);
  }
};

}  // namespace epona::nn
