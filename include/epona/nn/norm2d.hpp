// epona/nn/norm2d.hpp — the DC-AE's channel norms on NCHW maps: TritonRMSNorm2d ("trms2d":
// per pixel over channels, no mean subtraction, weight and bias) and BatchNorm2d in eval mode
// (running statistics), one type switched by the config's norm name; an activation can follow.
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/nn/conv2d.hpp"

namespace epona::nn {

enum class Norm2dKind { Rms, Batch };

inline const char* norm2d_name(Norm2dKind k) { return k == Norm2dKind::Batch ? "BatchNorm2d" : "RMSNorm2d"; }

// Parameters are float32 for every weight type T (they are vectors of C values).
// Names: `weight`, `bias` [C]; BatchNorm also `running_mean`, `running_var` [C] and the ignored
// int64 counter `num_batches_tracked`.
template <class B, class T>
struct Norm2d : Bindable<Norm2d<B, T>> {
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

  // x = act(norm(x)) in place; x (N, C, H, W).
  template <class Ctx>
  void forward_inplace(Ctx& ctx, Tensor<float, B>& x, ConvAct act = ConvAct::None) const {
    EPONA_CHECK(x.dim() == 4 && x.size(1) == channels, norm2d_name(kind), "(", channels,
                "): input must be (N, ", channels, ", H, W), got ", shape_str(x.shape()));
    EPONA_CHECK(!weight.empty(), norm2d_name(kind), "(", channels, "): weights not bound");
    const std::int64_t N = x.size(0), HW = x.size(2) * x.size(3);
    if (kind == Norm2dKind::Batch)
      batch_norm_2d(ctx, x.data(), x.data(), N, channels, HW, weight.data(), bias.data(), running_mean.data(),
                    running_var.data(), eps);
    else
      rms_norm_2d(ctx, x.data(), x.data(), N, channels, HW, weight.data(), bias.data(), eps);
    apply_conv_act(ctx, x.data(), x.numel(), act);
  }
};

}  // namespace epona::nn
