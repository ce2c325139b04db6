// epona/nn/blocks/qk_norm_transformer_layer.hpp — a pre-LN transformer layer with QK-LayerNorm
// over the full width before the head split and no biases: the MST's `CausalTimeBlock` and
// `SpaceBlock` (models/stt.py; they share the parameter layout), causal or not and with or
// without RoPE by the attention shape the caller gives. The float32 residual stream is updated
// in place; each residual add runs with the LayerNorm after it, the next layer's first norm
// included when the caller chains layers (`next`).
#pragma once

#include <cstdint>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/core/backend_capabilities.hpp"
#include "epona/core/tensor.hpp"
#include "epona/nn/attention.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/flops.hpp"
#include "epona/nn/layer_norm.hpp"
#include "epona/nn/linear.hpp"
#include "epona/nn/mlp.hpp"
#include "epona/nn/parameter.hpp"
#include "epona/nn/rope.hpp"

namespace epona::nn {

template <class B, class W>
struct QkNormTransformerLayer : Bindable<QkNormTransformerLayer<B, W>> {
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  LayerNorm<B> ln1, ln2, q_norm, k_norm;
  Linear<B, W> query, key, value, proj;
  SequentialMlp<B, W> mlp;

  QkNormTransformerLayer() = default;
  // width C, MLP hidden width, and the LayerNorms' eps.
  QkNormTransformerLayer(std::int64_t width, std::int64_t mlp_hidden, float eps)
      : ln1(width, eps, true), ln2(width, eps, true), q_norm(width, eps, true), k_norm(width, eps, true),
        query(width, width, false), key(width, width, false), value(width, width, false), proj(width, width, false),
        mlp(width, mlp_hidden, width, false, Gelu::Erf) {}

  template <class V>
  void visit_params(const std::string& p, V& v) {
    ln1.visit_params(p + "ln1.", v);
    ln2.visit_params(p + "ln2.", v);
    // key, value, query stacked in that order: one grouped product (key and value alone in the
    // pruned last block, whose queries are a subset of the rows).
    Linear<B, W>::visit_group(v, {{&key, p + "attn.key."}, {&value, p + "attn.value."}, {&query, p + "attn.query."}});
    proj.visit_params(p + "attn.proj.", v);
    q_norm.visit_params(p + "attn.q_norm.", v);
    k_norm.visit_params(p + "attn.k_norm.", v);
    mlp.visit_params(p + "mlp.", v);
  }

  // Scratch of one layer over n tokens of width C.
  struct Scratch {
    Tensor<A, B> u, q, k, v;  // (n, C); k, v, q one (3, n, C) block in that order (grouped product)
    Tensor<A, B> hidden;      // (n, mlp hidden)
  };
  template <class Alloc>
  static Scratch plan(Alloc& a, std::int64_t n, std::int64_t width, std::int64_t mlp_hidden) {
    auto u = a.template take<A>({n, width});
    auto kvq = a.template take<A>({3, n, width});
    return {u, kvq[2], kvq[0], kvq[1], a.template take<A>({n, mlp_hidden})};
  }

  // x (n, C) += attn(ln1 x); x += mlp(ln2 x) on rows [first, first + count) of x, the queries
  // (keys and values come from all n rows; the pruned last block updates a subset).
  // `rope` (or null) rotates q and k after their norms, table row r for row r (the space layers,
  // where q and k cover the same rows); `shape` arranges the tokens into sequences.
  // Each residual add runs with the LayerNorm after it:
  // with `normed`, s.u already holds ln1(x) (written by the previous layer's last add); with
  // `next` (the following layer, whose x is exactly the rows updated here), the last add also
  // writes next->ln1 of those rows into s.u.
  void operator()(Context& ctx, Tensor<float, B>& x, Scratch& s, std::int64_t first, std::int64_t count,
                  const RopeTable<B>* rope, const PackedAttention& shape, bool normed = false,
                  const QkNormTransformerLayer* next = nullptr) const {
    const std::int64_t n = x.size(0);
    auto rows = x.slice(first, first + count);
    auto u = s.u.slice(0, n), k = s.k.slice(0, n), v = s.v.slice(0, n);
    auto q = s.q.slice(0, count), o = s.u.slice(0, count), hidden = s.hidden.slice(0, count);
    if (!normed) ln1(ctx, x, u);
    project_kvq(ctx, u, s, first, count);
    if (rope || !attend_normalized(ctx, q, k, v, o, shape)) {
      normalize_qk(ctx, q, k, rope, shape.heads);
      packed_attention(ctx, q.data(), k.data(), v.data(), o.data(), shape);  // the output reuses u
    }
    add_branch(ctx, proj, o, rows, q, &ln2, o);  // float32 residual += projection; o = ln2(x)
    mlp.fc1(ctx, o, hidden, mlp.fc1_epilogue());
    add_branch(ctx, mlp.fc2, hidden, rows, q, next ? &next->ln1 : nullptr, o);
  }

  // s.k, s.v = key, value of all rows of u; s.q = query of rows [first, first + count). One
  // grouped product where the backend has it (the query joins it where all rows are queries).
  void project_kvq(Context& ctx, const Tensor<A, B>& u, Scratch& s, std::int64_t first, std::int64_t count) const {
    const std::int64_t n = u.size(0), C = u.size(-1);
    auto q = s.q.slice(0, count);
    if (!Linear<B, W>::pair_available(ctx)) {
      auto k = s.k.slice(0, n), v = s.v.slice(0, n);
      key(ctx, u, k);
      value(ctx, u, v);
    } else {
      const std::int64_t apart = s.v.data() - s.k.data();  // plan: one block, k, v, q in that order
      EPONA_CHECK(s.q.data() - s.v.data() == apart, "MST layer scratch: k, v, q are not equally far apart");
      std::vector<const Linear<B, W>*> layers{&key, &value};
      if (count == n) layers.push_back(&query);
      Linear<B, W>::group(ctx, layers, u.data(), C, 0, n, s.k.data(), C, apart);
      if (count == n) return;
    }
    query(ctx, u.slice(first, first + count), q);
  }

  // rows (float32) += layer(in), then out = norm(rows) unless norm is null. The product adds to
  // the residual itself where the backend can (linear_accumulate: the branch is not rounded to
  // the activation type, and the norm pass reads the residual alone); otherwise the branch is
  // written to the scratch `branch` and added by the norm's pass.
  void add_branch(Context& ctx, const Linear<B, W>& layer, const Tensor<A, B>& in, Tensor<float, B>& rows,
                  Tensor<A, B>& branch, const LayerNorm<B>* norm, Tensor<A, B>& out) const {
    if constexpr (ResidualGemm<Context, A, W>) {
      if (residual_gemm_enabled(ctx)) {
        linear_accumulate(ctx, in, layer.weight, rows);
        if (norm) (*norm)(ctx, rows, out);
        return;
      }
    }
    layer(ctx, in, branch);
    if (norm) norm->add_and_normalize(ctx, rows, branch, out);
    else add_inplace(ctx, rows.data(), branch.data(), rows.numel());
  }

  // o = attention(q_norm(q), k_norm(k), v) in one kernel where the backend has one for this shape
  // (CUDA: the time layers' sequences of <= 16 frames, attention_qk_layer_norm); q and k are then
  // left as the products. False: nothing done.
  bool attend_normalized(Context& ctx, const Tensor<A, B>& q, const Tensor<A, B>& k, const Tensor<A, B>& v,
                         Tensor<A, B>& o, const PackedAttention& shape) const {
    if constexpr (ShortAttentionQkNorm<Context, A>) {
      return attention_qk_layer_norm(ctx, q.data(), k.data(), v.data(), o.data(), attention_shape<B>(shape),
                                     q_norm.weight.data(), q_norm.bias.data(), q_norm.eps, k_norm.weight.data(),
                                     k_norm.bias.data(), k_norm.eps);
    } else {
      return false;
    }
  }

  // q = q_norm(q), k = k_norm(k), then the rotation: one launch on the GPU where its fused
  // kernel applies (layer_norm_rope_qk: bf16 rounded once, after the rotation, as the official
  // float32 q/k are rounded by the attention), the ops in turn otherwise (rounding twice in bf16).
  void normalize_qk(Context& ctx, Tensor<A, B>& q, Tensor<A, B>& k, const RopeTable<B>* rope,
                    std::int64_t heads) const {
    const std::int64_t C = q.size(-1), head_dim = C / heads;
    EPONA_CHECK(!rope || (q.size(0) == k.size(0) && rope->rows() >= q.size(0) && 2 * rope->pairs() == head_dim),
                "MST RoPE: table (", rope ? rope->rows() : 0, " rows, ", rope ? rope->pairs() : 0,
                " pairs) for q/k of ", q.size(0), "/", k.size(0), " rows and head_dim ", head_dim);
    if constexpr (QkLayerNormRope<Context, A>) {
      const float* cos = rope ? rope->cos.data() : nullptr;
      const float* sin = rope ? rope->sin.data() : nullptr;
      if (layer_norm_rope_qk(ctx, q.data(), q.size(0), k.data(), k.size(0), C, q_norm.weight.data(),
                             q_norm.bias.data(), q_norm.eps, k_norm.weight.data(), k_norm.bias.data(), k_norm.eps,
                             head_dim, cos, sin))
        return;
    }
    q_norm(ctx, q, q);
    k_norm(ctx, k, k);
    if (rope) apply_rope_qk(ctx, q.data(), k.data(), q.size(0), C, heads, *rope);
  }

  Flops flops(std::int64_t n, std::int64_t count) const {
    return {key.flops(n) + value.flops(n) + query.flops(count) + proj.flops(count) + mlp.flops(count), 0};
  }
};

}  // namespace epona::nn
