// epona/nn/layer_norm.hpp — nn.LayerNorm over the last dimension, affine (weight, bias; the
// MST's eps 1e-5) or parameter-free (the DiTs' eps 1e-6 norms, elementwise_affine=False).
// The affine parameters stay float32 whatever the weight dtype (they are tiny).
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::nn {

template <class B>
struct LayerNorm : Bindable<LayerNorm<B>> {
  using Context = BackendContext<B>;

  std::int64_t width = 0;
  float eps = 1e-5f;
  bool affine = true;
  Tensor<float, B> weight, bias;  // (width) each, empty when not affine

  LayerNorm() = default;
  LayerNorm(std::int64_t n, float epsilon, bool with_affine) : width(n), eps(epsilon), affine(with_affine) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    if (!affine) return;
    v.param(prefix + "weight", weight, {width});
    v.param(prefix + "bias", bias, {width});
  }

  // y = LN(x) row by row over the last dimension; x and y may be the same tensor. Statistics in
  // float32; x and y may have different storage types (the MST's float32 residual stream
  // normalised into a bf16 GEMM input, or a bf16 projection normalised into float32).
  template <class TX, class TY>
  void operator()(Context& ctx, const Tensor<TX, B>& x, Tensor<TY, B>& y) const {
    EPONA_CHECK(x.dim() >= 1 && x.size(-1) == width && y.numel() == x.numel(), "LayerNorm(", width,
                "): input ", shape_str(x.shape()), ", output ", shape_str(y.shape()));
    layer_norm(ctx, x.data(), y.data(), x.numel() / width, width, affine ? weight.data() : nullptr,
               affine ? bias.data() : nullptr, eps);
  }

  // x += y, then out = LN(x): a residual update and this norm in one pass on the GPU (the MST's
  // float32 residual stream, its bf16 branch and the bf16 GEMM input). out must not overlap x, y.
  template <class TX, class TY, class TO>
  void add_and_normalize(Context& ctx, Tensor<TX, B>& x, const Tensor<TY, B>& y, Tensor<TO, B>& out) const {
    EPONA_CHECK(x.dim() >= 1 && x.size(-1) == width && y.numel() == x.numel() && out.numel() == x.numel(),
                "LayerNorm(", width, ") after a residual add: residual ", shape_str(x.shape()), ", branch ",
                shape_str(y.shape()), ", output ", shape_str(out.shape()));
    add_layer_norm(ctx, x.data(), y.data(), out.data(), x.numel() / width, width, affine ? weight.data() : nullptr,
                   affine ? bias.data() : nullptr, eps);
  }
};

}  // namespace epona::nn
