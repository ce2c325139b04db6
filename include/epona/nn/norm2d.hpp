// epona/nn/norm2d.hpp — the DC-AE's channel norms on feature maps: TritonRMSNorm2d ("trms2d":
// per pixel over channels, no mean subtraction, weight and bias) and BatchNorm2d in eval mode
// (running statistics), one type switched by the config's norm name; an activation can follow,
// or the normalised branch is added to a residual (fused in one pass on channels-last backends).
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/cpu/elementwise.hpp"
#include "epona/nn/conv2d.hpp"
#include "epona/nn/feature_map.hpp"

namespace epona::nn {

enum class Norm2dKind { Rms, Batch };

inline const char* norm2d_name(Norm2dKind k) { return k == Norm2dKind::Batch ? "BatchNorm2d" : "RMSNorm2d"; }

// Parameters are float32 for every weight type T (they are vectors of C values).
// Names: `weight`, `bias` [C]; BatchNorm also `running_mean`, `running_var` [C] and the ignored
// int64 counter `num_batches_tracked`.
template <class B, class T>
struct Norm2d : Bindable<Norm2d<B, T>> {
  using Act = activation_t<B, T>;
  using Map = Tensor<Act, B>;

  Norm2dKind kind = Norm2dKind::Rms;
  std::int64_t channels = 0;
  float eps = 1e-5f;  // both norms: TritonRMSNorm2d inherits nn.LayerNorm's default, BatchNorm2d has its own
  Tensor<float, B> weight, bias, running_mean, running_var;

  Norm2d() = default;
  Norm2d(Norm2dKind k, std::int64_t c, float epsilon = 1e-5f) : kind(k), channels(c), eps(epsilon) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    v.param(prefix + "weight", weight, {channels});
    v.param(prefix + "bias", bias, {channels});
    if (kind != Norm2dKind::Batch) return;
    v.param(prefix + "running_mean", running_mean, {channels});
    v.param(prefix + "running_var", running_var, {channels});
    v.counter(prefix + "num_batches_tracked");
  }

  // x = act(norm(x)) in place.
  template <class Ctx>
  void forward_inplace(Ctx& ctx, Map& x, ConvAct act = ConvAct::None) const {
    const MapDims d = checked_dims(x);
    if (kind == Norm2dKind::Batch)
      batch_norm_2d(ctx, x.data(), x.data(), d.batch, channels, d.pixels(), weight.data(), bias.data(),
                    running_mean.data(), running_var.data(), eps);
    else
      rms_norm_2d(ctx, x.data(), x.data(), d.batch, channels, d.pixels(), weight.data(), bias.data(), eps);
    apply_conv_act(ctx, x.data(), x.numel(), act);
  }

  // residual += norm(branch) (the post-norm residual branch of every DC-AE block). Channels-last
  // backends do it in one pass (norm_2d_add); branch is then left unchanged. Otherwise branch is
  // normalised in place and added.
  template <class Ctx>
  void add_to(Ctx& ctx, Map& branch, Map& residual) const {
    const MapDims d = checked_dims(branch);
    check_shape(residual, branch.shape(), "residual of the normalised branch");
    if constexpr (channels_last_maps<B>) {
      norm_2d_add(ctx, branch.data(), residual.data(), d.batch * d.pixels(), channels, weight.data(), bias.data(),
                  kind == Norm2dKind::Batch ? running_mean.data() : nullptr,
                  kind == Norm2dKind::Batch ? running_var.data() : nullptr, eps);
    } else {
      forward_inplace(ctx, branch);
      add_inplace(ctx, residual.data(), branch.data(), residual.numel());
    }
  }

 private:
  MapDims checked_dims(const Map& x) const {
    const std::string what = std::string(norm2d_name(kind)) + "(" + std::to_string(channels) + ")";
    const MapDims d = map_dims(x, what, channels);
    EPONA_CHECK(!weight.empty(), what, ": weights not bound");
    return d;
  }
};

}  // namespace epona::nn
