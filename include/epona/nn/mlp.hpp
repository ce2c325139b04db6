// epona/nn/mlp.hpp — the two-layer perceptrons of the world model: Linear → GELU → Linear as
// an nn.Sequential with indices 0 and 2 (the MST's exact-GELU MLPs without bias, the DiTs'
// tanh-GELU MLPs with bias), and FLUX's MLPEmbedder (in_layer → SiLU → out_layer). The
// activation runs in the first GEMM's epilogue.
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/linear.hpp"

namespace epona::nn {

enum class Gelu { Erf, Tanh };

template <class B, class T>
struct SequentialMlp : Bindable<SequentialMlp<B, T>> {
  using Context = BackendContext<B>;
  using Epilogue = BackendEpilogue<B>;
  using A = Activation<B, T>;

  Linear<B, T> fc1, fc2;  // "<prefix>0.", "<prefix>2."
  Gelu gelu = Gelu::Erf;

  SequentialMlp() = default;
  SequentialMlp(std::int64_t in, std::int64_t hidden, std::int64_t out, bool bias, Gelu g)
      : fc1(in, hidden, bias), fc2(hidden, out, bias), gelu(g) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    fc1.visit_params(prefix + "0.", v);
    fc2.visit_params(prefix + "2.", v);
  }

  // Two MLPs of one shape with each layer's weights of both in one allocation (a's first;
  // Linear::visit_pair), for paired products.
  template <class V>
  static void visit_pair(V& v, SequentialMlp& a, const std::string& first, SequentialMlp& b, const std::string& second) {
    Linear<B, T>::visit_pair(v, a.fc1, first + "0.", b.fc1, second + "0.");
    Linear<B, T>::visit_pair(v, a.fc2, first + "2.", b.fc2, second + "2.");
  }

  // x (rows, in) -> y (rows, out); hidden (rows, hidden) is scratch.
  void operator()(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& hidden, Tensor<A, B>& y) const {
    fc1(ctx, x, hidden, fc1_epilogue());
    fc2(ctx, hidden, y);
  }
  // fc1's fused activation (for callers that run the two layers themselves, e.g. paired).
  Epilogue fc1_epilogue() const { return gelu == Gelu::Erf ? Epilogue::GeluErf : Epilogue::GeluTanh; }

  std::int64_t hidden_width() const { return fc1.out; }
  double flops(std::int64_t tokens) const { return fc1.flops(tokens) + fc2.flops(tokens); }
};

template <class B, class T>
struct MlpEmbedder : Bindable<MlpEmbedder<B, T>> {
  using Context = BackendContext<B>;
  using Epilogue = BackendEpilogue<B>;
  using A = Activation<B, T>;

  Linear<B, T> in_layer, out_layer;

  MlpEmbedder() = default;
  MlpEmbedder(std::int64_t in, std::int64_t hidden) : in_layer(in, hidden, true), out_layer(hidden, hidden, true) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    in_layer.visit_params(prefix + "in_layer.", v);
    out_layer.visit_params(prefix + "out_layer.", v);
  }

  void operator()(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& hidden, Tensor<A, B>& y) const {
    in_layer(ctx, x, hidden, Epilogue::Silu);
    out_layer(ctx, hidden, y);
  }

  double flops(std::int64_t tokens) const { return in_layer.flops(tokens) + out_layer.flops(tokens); }
};

}  // namespace epona::nn
