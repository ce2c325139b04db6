// epona/core/backend_capabilities.hpp — the optional fused kernels of the backend contract, one
// named concept each. Layer code asks `if constexpr (Capability<Context, A>)` and composes the
// separate passes where a backend lacks one; a backend that claims a capability static_asserts
// it (cuda/backend.cuh), so a kernel whose signature drifts breaks the build instead of sending
// the model down the slow path. The required kernels (linear, layer_norm, attention, ...) are
// called unqualified and fail to compile where missing; only the optional ones are named here.
//
// The calls are unqualified and resolve by argument-dependent lookup when a concept is checked
// (the context's namespace: epona::cpu, epona::cuda), so this header includes no backend.
// Which backend has which:
//   capability               CPU  CUDA
//   AddGatedNormFromInput     -    yes
//   JointQkNormRope           -    yes
//   ResidualGemm              -    yes
//   ShortAttentionQkNorm      -    yes
//   FusedFrameTokens          -    yes
//   QkLayerNormRope           -    yes
//   PairedGemm                -    yes
//   GroupedLinear             -    yes
//   ItemRowNorms              -    yes
#pragma once

#include <array>
#include <concepts>
#include <cstdint>
#include <vector>

#include "epona/core/backend_traits.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/core/tensor.hpp"

namespace epona {

// The backend of a kernel context (BackendOf, specialised beside each BackendTraits).
template <class Context> using ContextBackend = typename BackendOf<Context>::type;

// A row range of a packed [q | k | v] buffer, as JointQkNormRope takes them (nn::detail::QkRows
// has these members): keys of rows [first, end) normed with k_scale, queries of rows
// [q_first, end) with q_scale. The default segment type the contract is checked with.
struct QkNormRopeSegment {
  std::int64_t first = 0, q_first = 0, end = 0;
  const float* q_scale = nullptr;
  const float* k_scale = nullptr;
};

// x_out = x + gate ⊙ y, out = (1 + scale) ⊙ LN(x_out) + shift, reading x and writing x_out (a
// separate buffer or x itself) in one pass: a DiT's first block reads its condition rows in place.
template <class Context, class A>
concept AddGatedNormFromInput = requires(Context& ctx, const A* x, A* x_out, const A* y, const A* gate, A* out,
                                         std::int64_t rows, const A* shift, float eps) {
  add_gated_layer_norm_modulate(ctx, x, x_out, y, gate, out, rows, rows, shift, shift, eps);
};

// QK RMSNorm + RoPE of several row ranges (Segment: QkNormRopeSegment's members) of a packed
// [q | k | v] buffer in one launch: a double block's two streams, a single block's q and k; the
// same ranges of every item of a folded batch (QkItems) in that launch too.
template <class Context, class A, class Segment = QkNormRopeSegment, std::size_t S = 2>
concept JointQkNormRope = requires(Context& ctx, A* qkv, std::int64_t n, float eps, const float* table,
                                   const std::array<Segment, S>& parts, const QkItems& items) {
  qk_norm_rope(ctx, qkv, n, n, n, n, eps, table, table, parts);
  qk_norm_rope(ctx, qkv, n, n, n, n, eps, table, table, parts, items);
};

// rows (float32) += x · wᵀ inside the product (the residual branch not rounded to A), and
// residual_gemm_enabled(ctx): whether the context's policy takes that path.
template <class Context, class A, class W = A>
concept ResidualGemm = requires(Context& ctx, const Tensor<A, ContextBackend<Context>>& x,
                                const Tensor<W, ContextBackend<Context>>& w, Tensor<float, ContextBackend<Context>>& rows) {
  linear_accumulate(ctx, x, w, rows);
  { residual_gemm_enabled(ctx) } -> std::convertible_to<bool>;
};

// o = attention(LN_q(q), LN_k(k), v) in one kernel for the shapes it takes (the MST's time
// layers); returns false, with nothing done, for the others.
template <class Context, class A>
concept ShortAttentionQkNorm = requires(Context& ctx, const A* q, A* o, const AttentionShape& shape,
                                        const float* p, float eps) {
  { attention_qk_layer_norm(ctx, q, q, q, o, shape, p, p, eps, p, p, eps) } -> std::convertible_to<bool>;
};

// q = LN_q(q), k = LN_k(k) over the full width, then RoPE on both (table row r for row r; null
// tables: none), in one launch where the rows fit; returns false, with nothing done, otherwise.
template <class Context, class A>
concept QkLayerNormRope = requires(Context& ctx, A* q, std::int64_t n, const float* p, float eps) {
  { layer_norm_rope_qk(ctx, q, n, q, n, n, p, p, eps, p, p, eps, n, p, p) } -> std::convertible_to<bool>;
};

// The MST's frame tokens (FrameTokens) from the image projector's pre-norm rows in one pass;
// returns false, with nothing written, where it does not apply.
template <class Context, class A>
concept FusedFrameTokens = requires(Context& ctx, const A* image, const float* p, float* out, const FrameTokens& t) {
  { try_assemble_frame_tokens(ctx, image, p, p, p, p, out, t) } -> std::convertible_to<bool>;
};

// Whether GroupedLinear runs as one product on this context (its policy's pair_gemm).
template <class Context>
concept PairedGemm = requires(Context& ctx) {
  { pair_gemm_enabled(ctx) } -> std::convertible_to<bool>;
};

// Layers of one shape (weights T, activations A) as one batched product: y + i·y_stride =
// x + i·x_stride times weights[i]ᵀ plus biases[i], then the epilogue.
template <class Context, class A, class T = A>
concept GroupedLinear = requires(Context& ctx, const A* x, std::int64_t n, const std::vector<const T*>& weights,
                                 A* y, BackendEpilogue<ContextBackend<Context>> epilogue) {
  linear_group(ctx, x, n, n, weights, weights, y, n, n, n, n, n, epilogue);
};

// The modulated norms of the same rows of several batch items (NormItems), with and without the
// gated residual add before them, each in one launch: a DiT's folded batch, whose items have
// their own adaLN vectors. Without it the items run one by one.
template <class Context, class A>
concept ItemRowNorms = requires(Context& ctx, const A* x, A* out, float eps, const NormItems& items) {
  layer_norm_modulate_items(ctx, x, out, items.rows, x, x, eps, items);
  add_gated_layer_norm_modulate_items(ctx, x, out, x, x, out, items.rows, x, x, eps, items);
};

}  // namespace epona
