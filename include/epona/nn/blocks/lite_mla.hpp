// epona/nn/blocks/lite_mla.hpp — LiteMLA of EfficientViT as the DC-AE mix variant uses it (no
// multi-scale aggregation): 1x1 qkv conv (no bias), ReLU linear attention per 32-wide head with
// q/k/v interleaved per head, then 1x1 proj conv (no bias) and its RMSNorm2d. Returns the branch.
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/nn/conv2d.hpp"
#include "epona/nn/feature_map.hpp"
#include "epona/nn/norm2d.hpp"

namespace epona::nn {

// Names (under the branch prefix): `qkv.conv.weight` [3C, C, 1, 1], `proj.conv.weight` [C, C, 1, 1],
// `proj.norm.{weight,bias}` [C].
template <class B, class T>
struct LiteMLA : Bindable<LiteMLA<B, T>> {
  std::int64_t channels = 0, head_dim = 32;
  float eps = 1e-15f;  // added to the normaliser in float32 (it would underflow in fp16)
  Conv2d<B, T> qkv, proj_conv;
  Norm2d<B, T> proj_norm;

  LiteMLA() = default;
  LiteMLA(std::int64_t c, Norm2dKind norm, std::int64_t dim = 32, float epsilon = 1e-15f)
      : channels(c), head_dim(dim), eps(epsilon), qkv(c, 3 * c, 1, 1, false), proj_conv(c, c, 1, 1, false),
        proj_norm(norm, c) {
    EPONA_CHECK(dim > 0 && c % dim == 0, "LiteMLA: ", c, " channels are not a whole number of ", dim,
                "-wide heads");
  }
  std::int64_t heads() const { return channels / head_dim; }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    qkv.visit_params(prefix + "qkv.conv.", v);
    proj_conv.visit_params(prefix + "proj.conv.", v);
    proj_norm.visit_params(prefix + "proj.norm.", v);
  }

  using Act = activation_t<B, T>;
  using Map = Tensor<Act, B>;

  // x (a map of C channels) -> the branch output, same extents (the EfficientViT block adds x).
  // H·W > head_dim takes the linear evaluation order, otherwise the quadratic one, as the reference.
  template <class Ctx>
  Map forward(Ctx& ctx, const Map& x) const {
    Map y = attend_and_project(ctx, x);
    proj_norm.forward_inplace(ctx, y);
    return y;
  }
  // x += forward(x).
  template <class Ctx>
  void add_to(Ctx& ctx, Map& x) const {
    Map y = attend_and_project(ctx, x);
    proj_norm.add_to(ctx, y, x);
  }

 private:
  template <class Ctx>
  Map attend_and_project(Ctx& ctx, const Map& x) const {
    const MapDims d = map_dims(x, "LiteMLA(" + std::to_string(channels) + ")", channels);
    Map q_k_v = qkv.forward(ctx, x);     // 3C channels: per head [q, k, v]
    Map att = new_map<Act, B>(ctx, d);  // C channels
    relu_linear_attention(ctx, q_k_v.data(), att.data(), d.batch, heads(), head_dim, d.pixels(), eps);
    return proj_conv.forward(ctx, att);
  }
};

}  // namespace epona::nn
