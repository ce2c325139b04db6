// epona/nn/modulation.hpp — adaLN modulation of the FLUX blocks (`Modulation`, and the final
// layer's `adaLN_modulation`): m = Linear(SiLU(vec)) split into `chunks` consecutive vectors
// of width dim — (shift, scale, gate)[×2] for the blocks, (shift, scale) for the final layer.
// SiLU(vec) is shared by every modulation of a forward, so callers pass it in once computed;
// the samplers evaluate every modulation for all their steps at once (one GEMM of M = steps
// rows instead of one GEMV per step; docs/world-model.md, design notes) into columns of one table.
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/linear.hpp"

namespace epona::nn {

// The adaLN vectors of one modulated sublayer, each `dim` wide, in Modulation's chunk order:
// out = x + gate ⊙ f((1 + scale) ⊙ LN(x) + shift). gate is null for a (shift, scale) pair (the
// final layer's, or the next block's first norm fused into a residual add); all null: none.
template <class A>
struct AdaLn {
  const A* shift = nullptr;
  const A* scale = nullptr;
  const A* gate = nullptr;
  explicit operator bool() const { return shift != nullptr; }

  // The sublayer whose chunks start at chunk `first` of a modulation row (null row: none).
  static AdaLn at(const A* row, std::int64_t dim, std::int64_t first = 0, bool gated = true) {
    if (row == nullptr) return {};
    return {row + first * dim, row + (first + 1) * dim, gated ? row + (first + 2) * dim : nullptr};
  }
  static AdaLn norm_at(const A* row, std::int64_t dim, std::int64_t first = 0) { return at(row, dim, first, false); }
  // The same vectors `elems` elements further on (a batch item's own row of the table).
  AdaLn offset(std::int64_t elems) const {
    const auto move = [elems](const A* p) { return p ? p + elems : p; };
    return {move(shift), move(scale), move(gate)};
  }
};

template <class B, class T>
struct Modulation : Bindable<Modulation<B, T>> {
  using Context = BackendContext<B>;
  using A = Activation<B, T>;

  std::int64_t dim = 0;
  int chunks = 0;
  Linear<B, T> lin;

  Modulation() = default;
  Modulation(std::int64_t d, int n_chunks) : dim(d), chunks(n_chunks), lin(d, n_chunks * d, true) {}

  // `linear_prefix` is the Linear's own prefix: "img_mod.lin." or "adaLN_modulation.1.".
  template <class V>
  void visit_params(const std::string& linear_prefix, V& v) {
    lin.visit_params(linear_prefix, v);
  }

  // silu_vec (1, dim) = SiLU(vec); the chunks*dim outputs go to the front of `out` (a buffer
  // of at least that many floats, so one buffer serves modulations of any chunk count).
  void operator()(Context& ctx, const Tensor<A, B>& silu_vec, const Tensor<A, B>& out) const {
    EPONA_CHECK(out.numel() >= chunks * dim, "modulation output buffer of ", out.numel(), " floats, needs ",
                chunks * dim);
    auto m = Tensor<A, B>::view(out.data(), {1, chunks * dim}, out.storage());
    lin(ctx, silu_vec, m);
  }

  // Many vectors at once: silu_vecs (rows, dim) -> chunks*dim values per row into out, whose
  // rows are `ld` apart (a column block of a wider table).
  void rows(Context& ctx, const A* silu_vecs, std::int64_t rows, A* out, std::int64_t ld) const {
    lin.strided(ctx, silu_vecs, dim, rows, out, ld);
  }
  std::int64_t width() const { return chunks * dim; }

  double flops() const { return lin.flops(1); }
};

}  // namespace epona::nn
