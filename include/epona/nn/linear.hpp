// epona/nn/linear.hpp — nn.Linear: y = x·Wᵀ (+ b) with PyTorch's weight layout W (out, in),
// optionally followed by an activation fused into the GEMM epilogue. Weights in T (float or
// bf16); activations in Activation<B, T> (float on the CPU, T on the GPU). Mirrors
// torch.nn.Linear (keys `<prefix>weight`, `<prefix>bias`). Two layers of one shape can run as one
// batched product where the backend has it (pair: the DiT double blocks' two streams).
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::nn {

template <class B, class T>
struct Linear {
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

  // prefix names the module ("img_in." → "img_in.weight", "img_in.bias").
  void bind(const io::TensorMap&, const std::string& prefix, io::BindReport& report) {
    weight = bind_param<B, T>(report, prefix + "weight", {out, in});
    if (has_bias) bias = bind_param<B, T>(report, prefix + "bias", {out});
  }

  // x (..., in) -> y (..., out); y preallocated.
  void operator()(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& y,
                  Epilogue epilogue = Epilogue::None) const {
    linear(ctx, x, weight, bias, y, epilogue);
  }

  // Binds two layers of one shape (`first`, `second`: their prefixes) with their weights in one
  // allocation (2, out, in) and their biases in another (2, out), a's at index 0: a paired
  // product's weight stride is then one matrix, positive and small (cuBLASLt's bf16 batched
  // kernels take no negative strides, and two allocations may lie either way round).
  static void bind_pair(Linear& a, const std::string& first, Linear& b, const std::string& second,
                        io::BindReport& report) {
    EPONA_CHECK(a.in == b.in && a.out == b.out && a.has_bias == b.has_bias, "Linear::bind_pair: (", a.in, " -> ", a.out,
                ") with (", b.in, " -> ", b.out, ")");
    const auto both = [&](const std::string& name, const Shape& shape, Tensor<T, B>& ta, Tensor<T, B>& tb) {
      auto stacked = bind_stacked_params<B, T>(report, {first + name, second + name}, shape);
      if (!stacked.empty()) ta = stacked[0], tb = stacked[1];
    };
    both("weight", {a.out, a.in}, a.weight, b.weight);
    if (a.has_bias) both("bias", {a.out}, a.bias, b.bias);
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

  // Whether `pair` runs as one product on this backend (the GPU's strided-batched cuBLASLt
  // product, unless switched off), rather than as two.
  static bool pair_available(Context& ctx) {
    if constexpr (requires { pair_gemm_enabled(ctx); })
      return pair_gemm_enabled(ctx);
    else
      return false;
  }

  // This layer and `second` (same shape) on `rows` rows each: y = layer(x) and
  // y + y_stride = second(x + x_stride) (strides in elements, rows ldx / ldy apart inside each).
  void pair(Context& ctx, const Linear& second, const A* x, std::int64_t ldx, std::int64_t x_stride, std::int64_t rows,
            A* y, std::int64_t ldy, std::int64_t y_stride, Epilogue epilogue = Epilogue::None) const {
    EPONA_CHECK(second.in == in && second.out == out && second.has_bias == has_bias, "Linear::pair: (", in, " -> ",
                out, ") with (", second.in, " -> ", second.out, ")");
    const auto bias_of = [](const Linear& l) { return l.has_bias ? l.bias.data() : static_cast<const T*>(nullptr); };
    if constexpr (requires { linear_pair(ctx, x, ldx, x_stride, weight.data(), bias_of(*this), second.weight.data(),
                                         bias_of(second), y, ldy, y_stride, rows, out, in, epilogue); }) {
      linear_pair(ctx, x, ldx, x_stride, weight.data(), bias_of(*this), second.weight.data(), bias_of(second), y, ldy,
                  y_stride, rows, out, in, epilogue);
    } else {
      strided(ctx, x, ldx, rows, y, ldy, epilogue);
      second.strided(ctx, x + x_stride, ldx, rows, y + y_stride, ldy, epilogue);
    }
  }

  double flops(std::int64_t tokens) const { return 2.0 * double(tokens) * double(in) * double(out); }
};

}  // namespace epona::nn
