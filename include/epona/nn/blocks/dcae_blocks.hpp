// epona/nn/blocks/dcae_blocks.hpp — the residual blocks of DC-AE stages (efficientvit ResidualBlock
// wrappers, `main` = the branch): ResBlock (conv-act-conv-norm + x), EfficientViTBlock (LiteMLA
// then GLUMBConv, each + x), and the 2x resampling pairs ConvPixelUnshuffle + channel-averaging
// shortcut (down) and ConvPixelShuffle + channel-duplicating shortcut (up).
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/cpu/elementwise.hpp"
#include "epona/nn/conv2d.hpp"
#include "epona/nn/feature_map.hpp"
#include "epona/nn/blocks/glu_mbconv.hpp"
#include "epona/nn/blocks/lite_mla.hpp"
#include "epona/nn/norm2d.hpp"
#include "epona/nn/pixel_shuffle.hpp"

namespace epona::nn {

// ResBlock: out = x + norm(conv2(act(conv1(x) + b1))); conv2 has no bias, no act after the add.
// Names (under the op prefix): `main.conv1.conv.{weight,bias}`, `main.conv2.conv.weight`, `main.conv2.norm.*`.
// Channels-last backends fold an eval-mode BatchNorm into conv2 when the parameters are bound or
// randomised (`conv2_bn`, the backend's fold_batch_norm), so conv2 -> BN -> + x is one
// residual-adding conv (conv2d_residual); the official parameters stay as bound.
template <class B, class T>
struct ResBlock : Bindable<ResBlock<B, T>> {
  Conv2d<B, T> conv1, conv2;
  Norm2d<B, T> norm;
  ConvAct act = ConvAct::Silu;
  Conv2d<B, T> conv2_bn;  // conv2 with the BatchNorm folded in; empty where not folded

  ResBlock() = default;
  ResBlock(std::int64_t c, Norm2dKind n, ConvAct a)
      : conv1(c, c, 3), conv2(c, c, 3, 1, false), norm(n, c), act(a) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    conv1.visit_params(prefix + "main.conv1.conv.", v);
    conv2.visit_params(prefix + "main.conv2.conv.", v);
    norm.visit_params(prefix + "main.conv2.norm.", v);
    if constexpr (channels_last_maps<B> && requires(Tensor<T, B>& w) { v.conv_weight(prefix, w, Shape{}); })
      fold_norm();  // the visitor set new values
  }

  using Map = Tensor<activation_t<B, T>, B>;

  // x (a map of C channels), updated in place.
  template <class Ctx>
  void forward_inplace(Ctx& ctx, Map& x) const {
    if constexpr (channels_last_maps<B>) {
      if (!conv2_bn.weight.empty()) {
        const Map h = conv1.forward(ctx, x, act);
        const MapDims d = conv2_bn.output_dims(h);
        check_shape(x, h.shape(), "ResBlock input");
        conv2d_residual(ctx, h.data(), conv2_bn.weight.data(), conv2_bn.bias.data(), x.data(),
                        Conv2dShape{d.batch, conv2.in_channels, d.height, d.width, conv2.out_channels, conv2.kernel, 1});
        return;
      }
    }
    Map branch = conv2.forward(ctx, conv1.forward(ctx, x, act));
    norm.add_to(ctx, branch, x);
  }

 private:
  void fold_norm() {
    conv2_bn = Conv2d<B, T>();
    if (norm.kind != Norm2dKind::Batch || conv2.groups != 1 || conv2.has_bias || conv2.weight.empty() ||
        norm.weight.empty() || norm.bias.empty() || norm.running_mean.empty() || norm.running_var.empty())
      return;
    Conv2d<B, T> folded(conv2.in_channels, conv2.out_channels, conv2.kernel, 1, true);
    if (fold_batch_norm(conv2.weight, norm.weight, norm.bias, norm.running_mean, norm.running_var, norm.eps,
                        folded.weight, folded.bias))
      conv2_bn = std::move(folded);
  }
};

// EfficientViTBlock (EViT_GLU): x += LiteMLA(x) (`context_module.main.*`), then
// x += GLUMBConv(x) (`local_module.main.*`).
template <class B, class T>
struct EfficientViTBlock : Bindable<EfficientViTBlock<B, T>> {
  LiteMLA<B, T> context;
  GLUMBConv<B, T> local;

  EfficientViTBlock() = default;
  EfficientViTBlock(std::int64_t c, Norm2dKind n, ConvAct a, std::int64_t head_dim = 32, float mla_eps = 1e-15f,
                    std::int64_t expand = 4)
      : context(c, n, head_dim, mla_eps), local(c, n, a, expand) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    context.visit_params(prefix + "context_module.main.", v);
    local.visit_params(prefix + "local_module.main.", v);
  }

  template <class Ctx>
  void forward_inplace(Ctx& ctx, Tensor<activation_t<B, T>, B>& x) const {
    context.add_to(ctx, x);
    local.add_to(ctx, x);
  }
};

// ConvPixelUnshuffleDownSampleLayer(in -> out): 3x3 conv in -> out/4 (bias), unshuffle(2); with
// the averaging shortcut (a ResidualBlock) the names sit under `main.`: `[main.]conv.conv.*`.
template <class B, class T>
struct DownsampleBlock : Bindable<DownsampleBlock<B, T>> {
  static constexpr std::int64_t factor = 2;
  Conv2d<B, T> conv;
  std::int64_t out_channels = 0;
  bool shortcut = true;

  DownsampleBlock() = default;
  DownsampleBlock(std::int64_t in, std::int64_t out, bool with_shortcut)
      : conv(in, out / (factor * factor), 3), out_channels(out), shortcut(with_shortcut) {
    EPONA_CHECK(out % (factor * factor) == 0, "ConvPixelUnshuffle: ", out, " output channels are not divisible by ",
                factor * factor);
  }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    conv.visit_params(prefix + (shortcut ? "main.conv.conv." : "conv.conv."), v);
  }

  // in channels at H x W -> out channels at H/2 x W/2
  template <class Ctx>
  Tensor<activation_t<B, T>, B> forward(Ctx& ctx, const Tensor<activation_t<B, T>, B>& x) const {
    auto y = pixel_unshuffle(ctx, conv.forward(ctx, x), factor);
    if (shortcut) add_channel_average_down(ctx, x, y, factor);
    return y;
  }
};

// ConvPixelShuffleUpSampleLayer(in -> out): 3x3 conv in -> 4·out (bias), shuffle(2); with the
// duplicating shortcut the names sit under `main.`: `[main.]conv.conv.*`.
template <class B, class T>
struct UpsampleBlock : Bindable<UpsampleBlock<B, T>> {
  static constexpr std::int64_t factor = 2;
  Conv2d<B, T> conv;
  std::int64_t out_channels = 0;
  bool shortcut = true;

  UpsampleBlock() = default;
  UpsampleBlock(std::int64_t in, std::int64_t out, bool with_shortcut)
      : conv(in, out * factor * factor, 3), out_channels(out), shortcut(with_shortcut) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    conv.visit_params(prefix + (shortcut ? "main.conv.conv." : "conv.conv."), v);
  }

  // in channels at H x W -> out channels at 2H x 2W
  template <class Ctx>
  Tensor<activation_t<B, T>, B> forward(Ctx& ctx, const Tensor<activation_t<B, T>, B>& x) const {
    if (shortcut) return pixel_shuffle_add_duplicate(ctx, conv.forward(ctx, x), x, factor);
    return pixel_shuffle(ctx, conv.forward(ctx, x), factor);
  }
};

}  // namespace epona::nn
