// epona/nn/linear.hpp — nn.Linear: y = x·Wᵀ (+ b) with PyTorch's weight layout W (out, in),
// optionally followed by an activation fused into the GEMM epilogue. Weights in T (float or
// bf16); activations in Activation<B, T> (float on the CPU, T on the GPU). Mirrors
// torch.nn.Linear (keys `<prefix>weight`, `<prefix>bias`). Layers of one shape can run as one
// batched product where the backend has it (group: the DiT double blocks' two streams, the
// MST's key, value and query on one input).
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "epona/core/backend_capabilities.hpp"
#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::nn {

template <class B, class T>
struct Linear : Bindable<Linear<B, T>> {
  using Context = BackendContext<B>;
  using Epilogue = BackendEpilogue<B>;
  using A = Activation<B, T>;

  std::int64_t in = 0, out = 0;
  bool has_bias = false;
  Tensor<T, B> weight;  // (out, in)
  Tensor<T, B> bias;    // (out) or empty

  Linear() = default;
  Linear(std::int64_t in_features, std::int64_t out_features, bool with_bias)
      : in(in_features), out(out_features), has_bias(with_bias) {}

  // Same features in and out, and a bias on both or neither: layers that can be stacked and grouped.
  bool same_shape(const Linear& o) const { return in == o.in && out == o.out && has_bias == o.has_bias; }

  // prefix names the module ("img_in." → "img_in.weight", "img_in.bias").
  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    v.param(prefix + "weight", weight, {out, in});
    if (has_bias) v.param(prefix + "bias", bias, {out});
  }

  // x (..., in) -> y (..., out); y preallocated.
  void operator()(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& y,
                  Epilogue epilogue = Epilogue::None) const {
    linear(ctx, x, weight, bias, y, epilogue);
  }

  // Layers of one shape (each with its prefix) with their weights in one allocation
  // (count, out, in) and their biases in another (count, out), in the order given: a grouped
  // product's weight stride is then one matrix, positive and small (cuBLASLt's bf16 batched
  // kernels take no negative strides, and separate allocations may lie either way round).
  template <class V>
  static void visit_group(V& v, const std::vector<std::pair<Linear*, std::string>>& layers) {
    const Linear& a = *layers.front().first;
    for (const auto& [l, prefix] : layers)
      EPONA_CHECK(l->same_shape(a), "Linear group: ", prefix, " (", l->in, " -> ", l->out, ") with (", a.in, " -> ",
                  a.out, ")");
    const auto stack = [&](const std::string& name, const Shape& shape, Tensor<T, B> Linear::*member) {
      std::vector<StackedPart<T, B>> parts;
      for (const auto& [l, prefix] : layers) parts.push_back({&(l->*member), prefix + name});
      visit_stacked(v, std::span<const StackedPart<T, B>>(parts), shape);
    };
    stack("weight", {a.out, a.in}, &Linear::weight);
    if (a.has_bias) stack("bias", {a.out}, &Linear::bias);
  }
  template <class V>
  static void visit_pair(V& v, Linear& a, const std::string& first, Linear& b, const std::string& second) {
    visit_group(v, {{&a, first}, {&b, second}});
  }

  // The layer restricted to output features [begin, end): the rows of W and b (contiguous),
  // so a fused projection (qkv + mlp) can be evaluated in parts.
  Linear rows(std::int64_t begin, std::int64_t end) const {
    Linear part(in, end - begin, has_bias);
    part.weight = weight.slice(begin, end);
    if (has_bias) part.bias = bias.slice(begin, end);
    return part;
  }

  // Pointer form for strided rows: y[r*ldy + o] for r < rows (y may be a column block of a
  // wider buffer, x a row subset of one).
  void strided(Context& ctx, const A* x, std::int64_t ldx, std::int64_t rows, A* y, std::int64_t ldy,
               Epilogue epilogue = Epilogue::None) const {
    linear(ctx, x, ldx, weight.data(), has_bias ? bias.data() : static_cast<const T*>(nullptr), y, ldy, rows, out, in,
           epilogue);
  }

  // Whether `group` runs as one product on this backend (the GPU's strided-batched cuBLASLt
  // product, unless switched off), rather than one per layer.
  static bool pair_available(Context& ctx) {
    if constexpr (PairedGemm<Context>)
      return pair_gemm_enabled(ctx);
    else
      return false;
  }

  // Layers of one shape on `rows` rows each: y + i·y_stride = layers[i](x + i·x_stride) (strides
  // in elements, rows ldx / ldy apart inside each; x_stride 0: all on the same input). One
  // product where the backend has it and the weights lie equally far apart (bind_stacked).
  static void group(Context& ctx, const std::vector<const Linear*>& layers, const A* x, std::int64_t ldx,
                    std::int64_t x_stride, std::int64_t rows, A* y, std::int64_t ldy, std::int64_t y_stride,
                    Epilogue epilogue = Epilogue::None) {
    const Linear& a = *layers.front();
    std::vector<const T*> weights, biases;
    for (const Linear* l : layers) {
      EPONA_CHECK(l->same_shape(a), "Linear::group: (", l->in, " -> ", l->out, ") with (", a.in, " -> ", a.out, ")");
      weights.push_back(l->weight.data());
      biases.push_back(l->has_bias ? l->bias.data() : nullptr);
    }
    if constexpr (GroupedLinear<Context, A, T>) {
      linear_group(ctx, x, ldx, x_stride, weights, biases, y, ldy, y_stride, rows, a.out, a.in, epilogue);
    } else {
      for (std::size_t i = 0; i < layers.size(); ++i) {
        const auto at = static_cast<std::int64_t>(i);
        layers[i]->strided(ctx, x + at * x_stride, ldx, rows, y + at * y_stride, ldy, epilogue);
      }
    }
  }
  // This layer and `second` (same shape): group over the two.
  void pair(Context& ctx, const Linear& second, const A* x, std::int64_t ldx, std::int64_t x_stride, std::int64_t rows,
            A* y, std::int64_t ldy, std::int64_t y_stride, Epilogue epilogue = Epilogue::None) const {
    group(ctx, {this, &second}, x, ldx, x_stride, rows, y, ldy, y_stride, epilogue);
  }

  // This layer on `count` items of `rows` rows each: item i reads x + i·x_stride and writes
  // y + i·y_stride (elements; rows ldx / ldy apart inside an item). One batched product with a
  // shared weight where the backend groups products (a batch folded into a DiT's per-stream
  // rows, which lie between the other stream's), else one product per item.
  void items(Context& ctx, const A* x, std::int64_t ldx, std::int64_t x_stride, std::int64_t rows, A* y,
             std::int64_t ldy, std::int64_t y_stride, std::int64_t count, Epilogue epilogue = Epilogue::None) const {
    EPONA_CHECK(count >= 1, "Linear::items: ", count, " items");
    if (count == 1) return strided(ctx, x, ldx, rows, y, ldy, epilogue);
    group(ctx, std::vector<const Linear*>(static_cast<std::size_t>(count), this), x, ldx, x_stride, rows, y, ldy,
          y_stride, epilogue);
  }

  double flops(std::int64_t tokens) const { return 2.0 * double(tokens) * double(in) * double(out); }
};

}  // namespace epona::nn
