// epona/nn/attention.hpp — multi-head softmax attention over token-major packed buffers
// (one call per sequence group, no transposes), and the per-head QK RMSNorm of the FLUX
// blocks (`QKNorm`: query_norm/key_norm `scale` vectors, eps 1e-6). Heads own contiguous
// channel ranges [h·d, (h+1)·d), as in the official reshapes.
#pragma once

#include <cstdint>
#include <string>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/parameter.hpp"
#include "epona/nn/rope.hpp"

namespace epona::nn {

// Where q, k, v and the output of one attention call live: `seqs` independent sequences of
// `len` key tokens; token i of sequence s starts at base + s*seq_stride + i*token_stride.
// Queries may be fewer than keys (q_len; the pruned last blocks attend from a subset) — then
// q has its own strides and the call is unmasked.
struct PackedAttention {
  std::int64_t seqs = 1, len = 0, heads = 1, head_dim = 0;
  std::int64_t in_seq_stride = 0, in_token_stride = 0;    // k and v (and q unless q_len is set)
  std::int64_t out_seq_stride = 0, out_token_stride = 0;
  bool causal = false;
  std::int64_t q_len = -1, q_seq_stride = 0, q_token_stride = 0;  // q_len < 0: q like k and v

  std::int64_t queries() const { return q_len < 0 ? len : q_len; }
};

// The backend's description of a PackedAttention call.
template <class B>
typename BackendTraits<B>::AttentionShape attention_shape(const PackedAttention& p) {
  EPONA_CHECK(p.q_len < 0 || !p.causal, "attention: a causal mask needs as many queries as keys");
  typename BackendTraits<B>::AttentionShape a;
  a.seqs = p.seqs;
  a.heads = p.heads;
  a.lq = p.queries();
  a.lk = p.len;
  a.head_dim = p.head_dim;
  a.k_seq = a.v_seq = p.in_seq_stride;
  a.k_row = a.v_row = p.in_token_stride;
  a.q_seq = p.q_len < 0 ? p.in_seq_stride : p.q_seq_stride;
  a.q_row = p.q_len < 0 ? p.in_token_stride : p.q_token_stride;
  a.o_seq = p.out_seq_stride;
  a.o_row = p.out_token_stride;
  using Mask = typename BackendTraits<B>::Mask;
  a.mask = p.causal ? Mask::Causal : Mask::None;
  return a;
}

template <class Context, class T>
void packed_attention(Context& ctx, const T* q, const T* k, const T* v, T* o, const PackedAttention& p) {
  attention(ctx, q, k, v, o, attention_shape<typename BackendOf<Context>::type>(p));
}

// FLOPs of attention as nn/flops.hpp counts them (4·H·Lq·Lk·d per sequence).
inline double attention_flops(std::int64_t seqs, std::int64_t heads, std::int64_t lq, std::int64_t lk,
                              std::int64_t head_dim) {
  return 4.0 * double(seqs) * double(heads) * double(lq) * double(lk) * double(head_dim);
}

// QKNorm: RMSNorm per token and head with separate learned scales for queries and keys.
template <class B>
struct QkNorm : Bindable<QkNorm<B>> {
  using Context = BackendContext<B>;

  std::int64_t head_dim = 0;
  float eps = 1e-6f;
  Tensor<float, B> query_scale, key_scale;  // (head_dim) each

  QkNorm() = default;
  QkNorm(std::int64_t d, float epsilon) : head_dim(d), eps(epsilon) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    v.param(prefix + "query_norm.scale", query_scale, {head_dim});
    v.param(prefix + "key_norm.scale", key_scale, {head_dim});
  }

  // In place on `rows` tokens; q of token r starts at q + r*stride (heads side by side), k too.
  template <class T>
  void operator()(Context& ctx, T* q, T* k, std::int64_t rows, std::int64_t stride, std::int64_t heads) const {
    queries(ctx, q, rows, stride, heads);
    keys(ctx, k, rows, stride, heads);
  }
  template <class T>
  void queries(Context& ctx, T* q, std::int64_t rows, std::int64_t stride, std::int64_t heads) const {
    rms_norm_heads(ctx, q, rows, stride, heads, head_dim, query_scale.data(), eps);
  }
  template <class T>
  void keys(Context& ctx, T* k, std::int64_t rows, std::int64_t stride, std::int64_t heads) const {
    rms_norm_heads(ctx, k, rows, stride, heads, head_dim, key_scale.data(), eps);
  }

  // The same followed by RoPE with rows [first_row, first_row + rows) of `rope` (one pass on the GPU).
  template <class T>
  void queries_rope(Context& ctx, T* q, std::int64_t rows, std::int64_t stride, std::int64_t heads,
                    const RopeTable<B>& rope, std::int64_t first_row) const {
    norm_rope(ctx, q, rows, stride, heads, query_scale, rope, first_row);
  }
  template <class T>
  void keys_rope(Context& ctx, T* k, std::int64_t rows, std::int64_t stride, std::int64_t heads,
                 const RopeTable<B>& rope, std::int64_t first_row) const {
    norm_rope(ctx, k, rows, stride, heads, key_scale, rope, first_row);
  }

 private:
  template <class T>
  void norm_rope(Context& ctx, T* x, std::int64_t rows, std::int64_t stride, std::int64_t heads,
                 const Tensor<float, B>& scale, const RopeTable<B>& rope, std::int64_t first_row) const {
    EPONA_CHECK(first_row >= 0 && first_row + rows <= rope.rows() && 2 * rope.pairs() == head_dim, "QK-norm RoPE: rows [",
                first_row, ", ", first_row + rows, ") of a table of ", rope.rows(), " x ", rope.pairs(), " pairs, head dim ",
                head_dim);
    const std::int64_t pairs = rope.pairs();
    rms_norm_rope_heads(ctx, x, rows, stride, heads, head_dim, scale.data(), eps, rope.cos.data() + first_row * pairs,
                        rope.sin.data() + first_row * pairs);
  }
};

}  // namespace epona::nn
