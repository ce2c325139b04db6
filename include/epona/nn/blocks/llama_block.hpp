// epona/nn/blocks/llama_block.hpp — the LLaMA-style TransformerBlock of Epona's temporal DC-AE decoder
// (`causal_time_block.*`, `space_block.*`): RMSNorm (weight only) -> q/k/v -> 1-D RoPE -> SDPA
// (causal or full) -> wo, + x; RMSNorm -> SwiGLU FFN, + x. No biases. Rows of the token
// matrix form sequences through a strided layout, so time and space attention need no transposes.
#pragma once

#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/cpu/attention.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/cpu/elementwise.hpp"
#include "epona/cpu/gemm.hpp"
#include "epona/cpu/norm.hpp"
#include "epona/cpu/rope.hpp"
#include "epona/nn/conv2d.hpp"
#include "epona/nn/feature_map.hpp"

namespace epona::nn {

// How the rows of a (rows, dim) token matrix form attention sequences: `groups` independent
// blocks of seqs·length consecutive rows; inside a block, token t of sequence s is row
// s·seq_step + t·pos_step, and t is also its RoPE position.
//   time attention over (clip, frame, token) rows: seqs = L, length = F, seq_step = 1, pos_step = L
//   space attention over the same rows:            seqs = F, length = L, seq_step = L, pos_step = 1
struct TokenSequences {
  std::int64_t groups = 1, seqs = 1, length = 1, seq_step = 1, pos_step = 1;
  bool causal = false;
  std::int64_t rows() const { return groups * seqs * length; }
  // RoPE position of row r.
  std::int64_t position(std::int64_t r) const { return ((r % (seqs * length)) / pos_step) % length; }
};

// cos/sin (rows, head_dim/2) of the 1-D RoPE: pair j of row r turns by pos(r) · theta^(-2j/head_dim).
// Frequencies and angles are float32 as the reference builds them (precompute_freqs_cis).
inline void rope_table_1d(const TokenSequences& seq, std::int64_t head_dim, float theta, std::vector<float>& cos_t,
                          std::vector<float>& sin_t) {
  const std::int64_t pairs = head_dim / 2, rows = seq.rows();
  std::vector<float> freq(static_cast<std::size_t>(pairs));
  for (std::int64_t j = 0; j < pairs; ++j)
    freq[j] = 1.0f / std::pow(theta, static_cast<float>(2 * j) / static_cast<float>(head_dim));
  cos_t.resize(static_cast<std::size_t>(rows * pairs));
  sin_t.resize(static_cast<std::size_t>(rows * pairs));
  for (std::int64_t r = 0; r < rows; ++r)
    for (std::int64_t j = 0; j < pairs; ++j) {
      const float angle = static_cast<float>(seq.position(r)) * freq[j];
      cos_t[r * pairs + j] = static_cast<float>(std::cos(static_cast<double>(angle)));
      sin_t[r * pairs + j] = static_cast<float>(std::sin(static_cast<double>(angle)));
    }
}

// Names (under the block prefix): `attention.{wq,wk,wv,wo}.weight` [D, D],
// `feed_forward.{w1,w3}.weight` [hidden, D], `feed_forward.w2.weight` [D, hidden],
// `attention_norm.weight`, `ffn_norm.weight` [D] (float32).
template <class B, class T>
struct TransformerBlock : Bindable<TransformerBlock<B, T>> {
  std::int64_t dim = 32, heads = 8, ffn_hidden = 256;
  float norm_eps = 1e-5f, rope_theta = 1000.f;
  Tensor<T, B> wq, wk, wv, wo, w1, w2, w3;
  Tensor<float, B> attention_norm, ffn_norm;

  TransformerBlock() = default;
  TransformerBlock(std::int64_t d, std::int64_t h, std::int64_t hidden, float eps, float theta)
      : dim(d), heads(h), ffn_hidden(hidden), norm_eps(eps), rope_theta(theta) {
    EPONA_CHECK(h > 0 && d % h == 0 && (d / h) % 2 == 0, "TransformerBlock: ", h, " heads do not split dim ", d,
                " into even head dims");
  }
  std::int64_t head_dim() const { return dim / heads; }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    for (auto [name, w] : {std::pair{"wq", &wq}, {"wk", &wk}, {"wv", &wv}, {"wo", &wo}})
      v.param(prefix + "attention." + name + ".weight", *w, {dim, dim});
    v.param(prefix + "feed_forward.w1.weight", w1, {ffn_hidden, dim});
    v.param(prefix + "feed_forward.w2.weight", w2, {dim, ffn_hidden});
    v.param(prefix + "feed_forward.w3.weight", w3, {ffn_hidden, dim});
    v.param(prefix + "attention_norm.weight", attention_norm, {dim});
    v.param(prefix + "ffn_norm.weight", ffn_norm, {dim});
  }

  using Act = activation_t<B, T>;
  using Rows = Tensor<Act, B>;

  // x (rows, D) updated in place; cos/sin (backend memory) from rope_table_1d(seq, head_dim(), rope_theta).
  // The residual stream x stays float32 whatever T (as under the reference's autocast, where
  // x + bf16 branch promotes to float32); the norms feed the GEMMs in Act, which run in Act.
  template <class Ctx>
  void forward_inplace(Ctx& ctx, Tensor<float, B>& x, const TokenSequences& seq, const float* cos_t,
                       const float* sin_t) const {
    const std::int64_t rows = seq.rows(), D = dim;
    check_shape(x, {rows, D}, "TransformerBlock input");
    const Tensor<T, B> none;
    const auto make = [&](std::int64_t width) { return new_tensor<Act, B>(ctx, {rows, width}); };
    Rows h = normed(ctx, x, attention_norm);
    Rows q = make(D), k = make(D), v = make(D), o = make(D), proj = make(D);
    linear(ctx, h, wq, none, q);
    linear(ctx, h, wk, none, k);
    linear(ctx, h, wv, none, v);
    apply_rope(ctx, q.data(), rows, D, heads, head_dim(), cos_t, sin_t);
    apply_rope(ctx, k.data(), rows, D, heads, head_dim(), cos_t, sin_t);
    attend(ctx, q, k, v, o, seq);
    linear(ctx, o, wo, none, proj);
    add_inplace(ctx, x.data(), proj.data(), x.numel());

    Rows h2 = normed(ctx, x, ffn_norm);
    Rows gate = make(ffn_hidden), value = make(ffn_hidden);
    linear(ctx, h2, w1, none, gate);
    linear(ctx, h2, w3, none, value);
    gated_act(ctx, value.data(), gate.data(), gate.data(), rows, ffn_hidden, ffn_hidden, ffn_hidden, ConvAct::Silu);
    linear(ctx, gate, w2, none, proj);
    add_inplace(ctx, x.data(), proj.data(), x.numel());
  }

 private:
  // RMSNorm without bias: v · 1/sqrt(mean(v²) + eps) · weight, into a new tensor of Act.
  template <class Ctx>
  Rows normed(Ctx& ctx, const Tensor<float, B>& x, const Tensor<float, B>& weight) const {
    Rows h = new_tensor<Act, B>(ctx, x.shape());
    if constexpr (is_host_backend<B>) {
      copy(ctx, x.data(), h.data(), x.numel());
      rms_norm_heads(ctx, h.data(), x.size(0), dim, 1, dim, weight.data(), norm_eps);
    } else {
      rms_norm_rows(ctx, x.data(), h.data(), x.size(0), dim, weight.data(), norm_eps);
    }
    return h;
  }

  template <class Ctx>
  void attend(Ctx& ctx, const Rows& q, const Rows& k, const Rows& v, Rows& o, const TokenSequences& seq) const {
    const std::int64_t D = dim, group = seq.seqs * seq.length * D;
    using Mask = typename BackendTraits<B>::Mask;
    typename BackendTraits<B>::AttentionShape a;
    a.seqs = seq.seqs, a.heads = heads, a.lq = a.lk = seq.length, a.head_dim = head_dim();
    a.q_seq = a.k_seq = a.v_seq = a.o_seq = seq.seq_step * D;
    a.q_row = a.k_row = a.v_row = a.o_row = seq.pos_step * D;
    a.scale = 1.0f / std::sqrt(static_cast<float>(head_dim()));
    a.mask = seq.causal ? Mask::Causal : Mask::None;
    for (std::int64_t g = 0; g < seq.groups; ++g)
      attention(ctx, q.data() + g * group, k.data() + g * group, v.data() + g * group, o.data() + g * group, a);
  }
};

}  // namespace epona::nn
