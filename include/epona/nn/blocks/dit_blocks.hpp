// epona/nn/blocks/dit_blocks.hpp — the FLUX-style blocks shared by Epona's two DiTs
// (models/modules/dit_modules/layers.py): DoubleStreamBlock (separate condition and target
// streams, joint attention), SingleStreamBlock (one stream, fused qkv+MLP projection) and
// LastLayer (adaLN + Linear). All blocks work on one residual buffer z whose rows are
// [condition tokens | target tokens], so the streams' concatenation costs nothing. Blocks read
// their modulation vectors from a table computed before the sampling loop (FluxDiT), so a
// step only runs the token-wise work. Activations are Activation<B, W> (bf16 on the GPU, as
// the official residual streams under autocast). On the GPU a double block runs each layer's
// two per-stream products as one batched product where the streams' rows are close (StreamPair).
// A block reaches its modulation vectors through named views (nn/modulation.hpp: AdaLn), and
// DitTrunk (nn/blocks/dit_trunk.hpp) chains the blocks with each fusion in place.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <string>

#include "epona/core/arena.hpp"
#include "epona/core/tensor.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/attention.hpp"
#include "epona/nn/flops.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/layer_norm.hpp"
#include "epona/nn/linear.hpp"
#include "epona/nn/mlp.hpp"
#include "epona/nn/parameter.hpp"
#include "epona/nn/modulation.hpp"
#include "epona/nn/rope.hpp"

namespace epona::nn {

// Widths of a DiT's blocks; the norms' eps are the FLUX layers' (LayerNorm and QK RMSNorm 1e-6).
// With `shards` > 1 the blocks are one shard of a tensor-parallel group (core/tensor_parallel.hpp):
// heads and mlp_hidden stay the whole model's, the shard holds heads/shards heads (its attention
// width) and mlp_hidden/shards MLP columns, and the residual width `hidden` is whole.
struct DitWidths {
  std::int64_t hidden = 0, heads = 0, mlp_hidden = 0;
  float ln_eps = 1e-6f;
  float rms_eps = 1e-6f;
  std::int64_t shards = 1;
  std::int64_t head_dim() const { return hidden / heads; }
  std::int64_t shard_heads() const { return heads / shards; }
  std::int64_t attention_width() const { return shard_heads() * head_dim(); }  // q, k, v and the attention output
  std::int64_t shard_mlp() const { return mlp_hidden / shards; }
};

// Token ranges of the joint sequence.
struct JointRows {
  std::int64_t cond = 0, target = 0;
  std::int64_t total() const { return cond + target; }
};

// Whether a double block may run each layer's two per-stream products as one batched product
// over max(cond, target) = cond rows per stream: only where the target stream is at most as
// long (its padded rows then lie past the table, never inside the condition's) and nearly as
// long (the padding is wasted work): the VisDiT's 515 / 512, not the TrajDiT's 515 / 15.
inline bool streams_pairable(const JointRows& r) {
  return r.target > 0 && r.target <= r.cond && 10 * r.target >= 9 * r.cond;
}
// Rows past the joint table that paired products read and write (the target stream's item
// runs cond rows from row cond): scratch padding whose contents never reach a result.
inline std::int64_t paired_padding(const JointRows& r) { return streams_pairable(r) ? r.cond - r.target : 0; }

// How the items of a batched evaluation lie in a DitScratch: item b's rows start at row b·rows of
// every buffer (its joint rows plus padding), its modulation row at `mods + b·mod_stride`
// (elements; 0: one row for all) and its RoPE table at row b·rope_stride (0: one table for all).
// The blocks fold the items into the rows of their products and batch the attention over them;
// only the row-wise passes, whose vectors are an item's own, run item by item.
struct DitItems {
  std::int64_t count = 1, rows = 0, mod_stride = 0, rope_stride = 0;
};

// Activation buffers of one DiT evaluation of `items` batch items (`rows` = condition + target
// tokens each), shared by all blocks; A is the activation type. Every buffer holds each item's
// rows plus `pad` rows (paired_padding), which only paired products and products over whole
// items touch: their contents never reach a result.
template <class B, class A = float>
struct DitScratch {
  Tensor<A, B> z;         // (items·(rows + pad), D) residual stream: condition rows, then target rows
  Tensor<A, B> modulated; // (items·(rows + pad), D) (1 + scale)·LN(z) + shift
  Tensor<A, B> qkv;       // (items·(rows + pad), 3I) [q | k | v], heads contiguous inside each (I: attention width)
  Tensor<A, B> attn;      // (items·(rows + pad), I) attention output (double blocks)
  Tensor<A, B> mlp;       // (items·(rows + pad), Dm) MLP hidden (a shard's columns)
  Tensor<A, B> cat;       // (items·(rows + pad), I + Dm) single blocks: [attention | GELU(mlp)]
  Tensor<A, B> sub;       // (items·(rows + pad), D) a sublayer's output before its gate
  DitItems items;         // how the items lie (the caller sets the modulation and RoPE strides)

  template <class Alloc>
  static DitScratch plan(Alloc& a, std::int64_t rows, const DitWidths& w, std::int64_t pad = 0,
                         std::int64_t count = 1) {
    EPONA_CHECK(count >= 1 && rows >= 0 && pad >= 0, "DiT scratch: ", count, " items of ", rows, " + ", pad, " rows");
    const std::int64_t D = w.hidden, I = w.attention_width(), Dm = w.shard_mlp(), padded = count * (rows + pad);
    DitScratch s;
    s.z = a.template take<A>({padded, D});
    s.modulated = a.template take<A>({padded, D});
    s.qkv = a.template take<A>({padded, 3 * I});
    s.attn = a.template take<A>({padded, I});
    s.mlp = a.template take<A>({padded, Dm});
    s.cat = a.template take<A>({padded, I + Dm});
    s.sub = a.template take<A>({padded, D});
    s.items = {count, rows + pad, 0, 0};
    return s;
  }
  // Sized for the joint rows, padded where the double blocks pair their streams' products.
  template <class Alloc>
  static DitScratch plan(Alloc& a, const JointRows& rows, const DitWidths& w, std::int64_t count = 1) {
    return plan(a, rows.total(), w, paired_padding(rows), count);
  }

  // Rows of one item that every buffer a double block's GEMM reads or writes holds.
  std::int64_t gemm_rows() const {
    return std::min({modulated.size(0), qkv.size(0), attn.size(0), mlp.size(0), sub.size(0)}) / items.count;
  }
};

// The second queue a block may overlap work on (a second CUDA stream; the CPU runs in order).
template <class B> using SideQueue = typename BackendTraits<B>::SideQueue;

namespace detail {
// y = (1 + scale) ⊙ LN(x) + shift over `rows` rows of x starting at `first`; with `src`, those
// rows are read from src instead of x.
template <class Context, class B, class A>
void modulate_rows(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& y, std::int64_t first, std::int64_t rows,
                   const AdaLn<A>& m, float eps, const A* src = nullptr) {
  const std::int64_t D = x.size(-1);
  layer_norm_modulate(ctx, src ? src : x.data() + first * D, y.data() + first * D, rows, D, m.shift, m.scale, eps);
}

// x += gate ⊙ y over `rows` rows of width n, then, with `next`, out = its modulated norm of the
// updated rows (the next sublayer's input, in the same pass).
template <class Context, class A>
void add_gated_then_norm(Context& ctx, A* x, const A* y, const A* gate, A* out, std::int64_t rows, std::int64_t n,
                         const AdaLn<A>& next, float eps) {
  if (next)
    add_gated_layer_norm_modulate(ctx, x, y, gate, out, rows, n, next.shift, next.scale, eps);
  else
    add_gated(ctx, x, y, gate, rows, n);
}

// x_out = x + gate ⊙ y, then out = (1 + scale) ⊙ LN(x_out) + shift, with x read from `x` and the
// update written to x_out (x_out may be x): one pass where the backend has the kernel with a
// separate input (the GPU), else a copy and the in-place pass.
template <class Context, class A>
void add_gated_norm_from(Context& ctx, const A* x, A* x_out, const A* y, const A* gate, A* out, std::int64_t rows,
                         std::int64_t n, const A* shift, const A* scale, float eps) {
  if constexpr (AddGatedNormFromInput<Context, A>) {
    add_gated_layer_norm_modulate(ctx, x, x_out, y, gate, out, rows, n, shift, scale, eps);
  } else {
    if (x != x_out) copy(ctx, x, x_out, rows * n);
    add_gated_layer_norm_modulate(ctx, x_out, y, gate, out, rows, n, shift, scale, eps);
  }
}

// modulate_rows over rows [first, first + rows) of every item (their vectors each item's own;
// src, when given, holds the items' rows contiguously): one launch where the backend has
// ItemRowNorms, else item by item.
template <class Context, class B, class A>
void modulate_items(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& y, std::int64_t first, std::int64_t rows,
                    const AdaLn<A>& m, float eps, const DitItems& items, const A* src = nullptr) {
  const std::int64_t D = x.size(-1);
  if constexpr (ItemRowNorms<Context, A>) {
    if (items.count > 1) {
      const NormItems ni{items.count, rows, items.rows, src ? rows : items.rows, items.mod_stride};
      layer_norm_modulate_items(ctx, src ? src : x.data() + first * D, y.data() + first * D, D, m.shift, m.scale, eps,
                                ni);
      return;
    }
  }
  for (std::int64_t b = 0; b < items.count; ++b)
    modulate_rows(ctx, x, y, b * items.rows + first, rows, m.offset(b * items.mod_stride), eps,
                  src ? src + b * rows * D : src);
}

// x_out = x + gate ⊙ y, then out = the `next` modulated norm of x_out (none: the add alone), over
// `rows` rows of width n of every item: x_out, y and out point at item 0's rows (items.rows
// apart), x at its residual input (x_stride rows apart; x == x_out: in place), gate and next at
// its vectors. One launch where the backend has ItemRowNorms, else item by item.
template <class Context, class A>
void add_gated_norm_items(Context& ctx, const A* x, A* x_out, const A* y, const A* gate, A* out, std::int64_t rows,
                          std::int64_t n, const AdaLn<A>& next, float eps, const DitItems& items, std::int64_t x_stride) {
  if constexpr (ItemRowNorms<Context, A>) {
    if (items.count > 1 && next) {
      const NormItems ni{items.count, rows, items.rows, x_stride, items.mod_stride};
      add_gated_layer_norm_modulate_items(ctx, x, x_out, y, gate, out, n, next.shift, next.scale, eps, ni);
      return;
    }
  }
  for (std::int64_t b = 0; b < items.count; ++b) {
    const std::int64_t at = b * items.rows * n, mod = b * items.mod_stride;
    const A* xb = x + b * x_stride * n;
    if (next) {
      const AdaLn<A> nb = next.offset(mod);
      add_gated_norm_from(ctx, xb, x_out + at, y + at, gate + mod, out + at, rows, n, nb.shift, nb.scale, eps);
    } else {
      if (xb != x_out + at) copy(ctx, xb, x_out + at, rows * n);
      add_gated_then_norm(ctx, x_out + at, y + at, gate + mod, out + at, rows, n, next, eps);
    }
  }
}

// Rows of a packed [q | k | v] buffer (rows 3D wide) that share one QK-norm: the keys of rows
// [first, end) and the queries of rows [q_first, end) (a pruned block's few queries).
template <class B>
struct QkRows {
  std::int64_t first = 0, q_first = 0, end = 0;
  const QkNorm<B>* norm = nullptr;
  const float* q_scale = nullptr;  // norm's, for the backend's joint kernel
  const float* k_scale = nullptr;
  QkRows(std::int64_t f, std::int64_t q, std::int64_t e, const QkNorm<B>& n)
      : first(f), q_first(q), end(e), norm(&n), q_scale(n.query_scale.data()), k_scale(n.key_scale.data()) {}
};

// QK RMSNorm + RoPE (rows of the joint table by token index) of every range in `parts`: one
// launch where the backend has the joint kernel (the GPU: a double block's two streams, or a
// single block's queries and keys), else one norm + RoPE call per range and kind.
template <class B, class A, std::size_t S>
void qk_norm_rope_rows(BackendContext<B>& ctx, A* qkv, const DitWidths& w, const RopeTable<B>& rope,
                       const std::array<QkRows<B>, S>& parts) {
  const std::int64_t I = w.attention_width(), hd = w.head_dim(), heads = w.shard_heads();
  if constexpr (JointQkNormRope<BackendContext<B>, A, QkRows<B>, S>) {
    for (const auto& p : parts)
      EPONA_CHECK(p.end <= rope.rows() && 2 * rope.pairs() == hd && p.norm->eps == parts[0].norm->eps,
                  "QK-norm RoPE: rows up to ", p.end, " of a table of ", rope.rows(), " x ", rope.pairs(),
                  " pairs, head dim ", hd);
    qk_norm_rope(ctx, qkv, 3 * I, I, heads, hd, parts[0].norm->eps, rope.cos.data(), rope.sin.data(), parts);
  } else {
    for (const auto& p : parts) {
      p.norm->queries_rope(ctx, qkv + p.q_first * 3 * I, p.end - p.q_first, 3 * I, heads, rope, p.q_first);
      p.norm->keys_rope(ctx, qkv + p.first * 3 * I + I, p.end - p.first, 3 * I, heads, rope, p.first);
    }
  }
}
// Item b's RoPE table (`rows` rows of it).
template <class B>
RopeTable<B> item_rope(const RopeTable<B>& rope, const DitItems& items, std::int64_t b, std::int64_t rows) {
  if (items.count == 1) return rope;
  const std::int64_t first = b * items.rope_stride;
  return {rope.cos.slice(first, first + rows), rope.sin.slice(first, first + rows)};
}

// qk_norm_rope_rows over the same ranges of every item (each item's rows and RoPE table where
// `items` puts them; `rope` is item 0's table onwards): one launch where the backend has the
// joint kernel, else item by item.
template <class B, class A, std::size_t S>
void qk_norm_rope_items(BackendContext<B>& ctx, A* qkv, const DitWidths& w, const RopeTable<B>& rope,
                        const std::array<QkRows<B>, S>& parts, const DitItems& items) {
  std::int64_t end = 0;
  for (const auto& p : parts) end = std::max(end, p.end);
  if constexpr (JointQkNormRope<BackendContext<B>, A, QkRows<B>, S>) {
    if (items.count > 1) {
      const std::int64_t I = w.attention_width(), last = (items.count - 1) * items.rope_stride + end;
      EPONA_CHECK(last <= rope.rows() && 2 * rope.pairs() == w.head_dim() && parts[0].norm->eps == parts[S - 1].norm->eps,
                  "QK-norm RoPE: rows up to ", last, " of a table of ", rope.rows(), " x ", rope.pairs(), " pairs");
      qk_norm_rope(ctx, qkv, 3 * I, I, w.shard_heads(), w.head_dim(), parts[0].norm->eps, rope.cos.data(), rope.sin.data(),
                   parts, QkItems{items.count, items.rows, items.rope_stride});
      return;
    }
  }
  for (std::int64_t b = 0; b < items.count; ++b)
    qk_norm_rope_rows<B>(ctx, qkv + b * items.rows * 3 * w.attention_width(), w, item_rope(rope, items, b, end), parts);
}
// Unmasked attention of queries at rows [q_first, q_first + q_rows) of the packed [q | k | v]
// buffer (rows in_stride apart) over all `rows` keys; output rows out_stride apart. Every item of
// a batched scratch in one launch: the items are sequences `items.rows` rows apart in qkv and out.
template <class B, class A>
void joint_attention(BackendContext<B>& ctx, const A* qkv, std::int64_t rows, std::int64_t q_first,
                     std::int64_t q_rows, const DitWidths& w, A* out, std::int64_t out_stride, std::int64_t in_stride,
                     const DitItems& items = {}) {
  const std::int64_t I = w.attention_width(), apart = items.count > 1 ? items.rows : 0;
  PackedAttention p{items.count, rows, w.shard_heads(), w.head_dim(), apart * in_stride, in_stride, apart * out_stride,
                    out_stride, false};
  p.q_len = q_rows;
  p.q_seq_stride = apart * in_stride;
  p.q_token_stride = in_stride;
  packed_attention(ctx, qkv + q_first * in_stride, qkv + I, qkv + 2 * I, out, p);
}

// y rows [y_first, y_first + rows) of each item = layer(x rows [x_first, ...) of the item); x and
// y hold their items `items.rows` rows apart. With `whole` (the rows between one item's range and
// the next item's are scratch the product may overwrite) and little between them, one product
// over the whole span; else one batched product over the items.
template <class Layer, class Context, class A>
void items_linear(const Layer& layer, Context& ctx, const A* x, std::int64_t ldx, std::int64_t x_first,
                  std::int64_t rows, A* y, std::int64_t ldy, std::int64_t y_first, const DitItems& items, bool whole,
                  typename Layer::Epilogue epilogue = Layer::Epilogue::None) {
  const std::int64_t R = items.rows, gap = R - rows;
  if (items.count == 1 || (whole && x_first == y_first && 8 * gap <= rows)) {
    const std::int64_t span = (items.count - 1) * R + rows;
    return layer.strided(ctx, x + x_first * ldx, ldx, span, y + y_first * ldy, ldy, epilogue);
  }
  layer.items(ctx, x + x_first * ldx, ldx, R * ldx, rows, y + y_first * ldy, ldy, R * ldy, items.count, epilogue);
}

// Adds up a shard's partial outputs (`count` elements at `data`) over its tensor-parallel group:
// nothing where the block is whole.
template <class Context, class A>
void sum_over_shards(Context& ctx, const ShardSum<Context, A>* sum, const DitWidths& w, A* data, std::int64_t count) {
  if (w.shards == 1) return;
  EPONA_CHECK(sum && sum->size() == w.shards, "DiT block: a shard of a group of ", w.shards,
              " needs the group's sum (DitTrunk::set_shard_sum)");
  sum->sum(ctx, data, count);
}

inline double joint_attention_flops(const DitWidths& w, std::int64_t q_rows, std::int64_t rows) {
  return attention_flops(1, w.shard_heads(), q_rows, rows, w.head_dim());
}
}  // namespace detail

// One stream of a double block: its modulation, attention projections and MLP.
template <class B, class W>
struct DoubleStream {
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  using Scratch = DitScratch<B, A>;
  Modulation<B, W> mod;
  Linear<B, W> qkv, proj;
  QkNorm<B> norm;
  SequentialMlp<B, W> mlp;

  DoubleStream() = default;
  explicit DoubleStream(const DitWidths& w)
      : mod(w.hidden, 6), qkv(w.hidden, 3 * w.attention_width(), true), proj(w.attention_width(), w.hidden, true),
        norm(w.head_dim(), w.rms_eps), mlp(w.hidden, w.shard_mlp(), w.hidden, true, Gelu::Tanh) {}

  // p names the stream ("double_blocks.0.img"): "<p>_mod.lin.", "<p>_attn.norm."; its Linear
  // layers ("<p>_attn.qkv.", "<p>_attn.proj.", "<p>_mlp.") are visited with the other
  // stream's (visit_layers).
  template <class V>
  void visit_own(const std::string& p, V& v) {
    mod.visit_params(p + "_mod.lin.", v);
    norm.visit_params(p + "_attn.norm.", v);
  }
  // The Linear layers of streams a and b, each layer's weights of both in one allocation (a's
  // first), so a paired product's weight stride is one matrix (Linear::visit_pair).
  template <class V>
  static void visit_layers(V& v, DoubleStream& a, const std::string& pa, DoubleStream& b, const std::string& pb) {
    Linear<B, W>::visit_pair(v, a.qkv, pa + "_attn.qkv.", b.qkv, pb + "_attn.qkv.");
    Linear<B, W>::visit_pair(v, a.proj, pa + "_attn.proj.", b.proj, pb + "_attn.proj.");
    SequentialMlp<B, W>::visit_pair(v, a.mlp, pa + "_mlp.", b.mlp, pb + "_mlp.");
  }

  // The stream's Linear layers, as StreamPair::linear picks them.
  static const Linear<B, W>& qkv_of(const DoubleStream& s) { return s.qkv; }
  static const Linear<B, W>& proj_of(const DoubleStream& s) { return s.proj; }
  static const Linear<B, W>& fc1_of(const DoubleStream& s) { return s.mlp.fc1; }
  static const Linear<B, W>& fc2_of(const DoubleStream& s) { return s.mlp.fc2; }

  double flops(std::int64_t rows) const { return qkv.flops(rows) + proj.flops(rows) + mlp.flops(rows); }
};

namespace detail {
// How a double block runs its two streams (condition rows [0, cond), target rows after them).
// Paired (the backend batches two products, streams_pairable, the scratch padded): each
// layer's two products are one batched product on the main queue, and the per-stream norms
// between them run there too, back to back (on two queues they gained nothing: VisDiT-100
// 263.6 ms either way on the H200). Otherwise one product per stream, the condition stream's
// work on the side queue between fork() and join(), overlapping the target stream's.
template <class B, class W>
class StreamPair {
 public:
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  using Epilogue = BackendEpilogue<B>;
  // One stream's rows, modulation vectors and layers, and the queue its work goes to.
  struct Part {
    const DoubleStream<B, W>* layers = nullptr;
    std::int64_t first = 0, rows = 0;
    AdaLn<A> attn, mlp;       // the stream's two sublayers' vectors
    AdaLn<A> next;            // the next block's first norm on these rows, or none
    const A* src = nullptr;   // the rows' residual input when s.z does not hold it yet, or null
    Context* ctx = nullptr;
  };

  // Item 0's rows and vectors (`items` says where the others' lie).
  StreamPair(Context& main, SideQueue<B>& queue, bool paired, Part cond, Part img, const DitItems& items)
      : main_(main), queue_(queue), paired_(paired), cond_(cond), img_(img), items_(items) {
    cond_.ctx = paired ? &main : &queue.side(main);
    img_.ctx = &main;
  }

  // Whether the block may pair: one item, rows close enough and the scratch padded for it (a
  // batch's items are folded into each stream's product instead).
  template <class Scratch>
  static bool pairs(Context& ctx, const Scratch& s, const JointRows& rows) {
    return s.items.count == 1 && Linear<B, W>::pair_available(ctx) && streams_pairable(rows) &&
           s.gemm_rows() >= 2 * rows.cond;
  }

  // A stretch where the streams touch disjoint rows (per-stream products: on two queues).
  void fork() {
    if (!paired_) queue_.fork(main_);
  }
  void join() {
    if (!paired_) queue_.join(main_);
  }

  // f(context, part) for the condition stream, then the target stream.
  template <class F>
  void each(F&& f) {
    f(*cond_.ctx, cond_);
    f(*img_.ctx, img_);
  }

  // y = layer(x) on each stream's rows of x and y; `layer` picks a stream's Linear.
  template <class Layer>
  void linear(Layer layer, const Tensor<A, B>& x, Tensor<A, B>& y, Epilogue epilogue = Epilogue::None) const {
    const std::int64_t ldx = x.size(-1), ldy = y.size(-1);
    if (paired_) {
      const std::int64_t apart = img_.first - cond_.first, rows = std::max(cond_.rows, img_.rows);
      layer(*cond_.layers).pair(main_, layer(*img_.layers), x.data() + cond_.first * ldx, ldx, apart * ldx, rows,
                                y.data() + cond_.first * ldy, ldy, apart * ldy, epilogue);
      return;
    }
    for (const Part* p : {&cond_, &img_})
      items_linear(layer(*p->layers), *p->ctx, x.data(), ldx, p->first, p->rows, y.data(), ldy, p->first, items_,
                   false, epilogue);
  }

 private:
  Context& main_;
  SideQueue<B>& queue_;
  bool paired_;
  Part cond_, img_;
  DitItems items_;
};
}  // namespace detail

// What the caller of a double block did already for its first sublayer.
struct DoubleBlockEntry {
  bool normed = false;  // s.modulated holds both streams' first modulated norm
  // The condition rows of s.qkv hold their q and k (QK-normed, rotated) and v: the sampler
  // ran the condition front ahead (condition_front; unpaired streams only).
  bool cond_qkv = false;
  static DoubleBlockEntry already_normed() { return {true, false}; }
};

template <class B, class W>
struct DoubleStreamBlock : Bindable<DoubleStreamBlock<B, W>> {
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  DitWidths widths;
  DoubleStream<B, W> img, cond;  // "img" is the target stream (latents or trajectory)
  const ShardSum<Context, A>* shard_sum = nullptr;  // the group's sum when widths.shards > 1

  DoubleStreamBlock() = default;
  explicit DoubleStreamBlock(const DitWidths& w) : widths(w), img(w), cond(w) {}

  // The condition stream's layers come first in each paired allocation: its rows come first.
  template <class V>
  void visit_params(const std::string& p, V& v) {
    img.visit_own(p + "img", v);
    cond.visit_own(p + "cond", v);
    DoubleStream<B, W>::visit_layers(v, cond, p + "cond", img, p + "img");
  }

  // Modulation vectors of this block in a table row: [img 6D | cond 6D].
  std::int64_t modulation_width() const { return 12 * widths.hidden; }
  void modulations(Context& ctx, const A* silu_vecs, std::int64_t n, A* table, std::int64_t ld) const {
    img.mod.rows(ctx, silu_vecs, n, table, ld);
    cond.mod.rows(ctx, silu_vecs, n, table + 6 * widths.hidden, ld);
  }

  // The condition stream's first sublayer up to the attention, for a caller that runs it
  // ahead (the sampler's pipelined front, DoubleBlockEntry::cond_qkv): modulated = the
  // condition rows' modulated norm of src (their residual input), then rows [0, cond) of the
  // qkv table `qkv` (3D wide) = qkv(modulated) with their QK RMSNorm + RoPE.
  // With `items`: every item's (src: (items, cond, D); modulated and qkv laid out as the items
  // of a DitScratch), as the block itself runs them.
  void condition_front(Context& ctx, const A* src, Tensor<A, B>& modulated, A* qkv, const JointRows& rows,
                       const RopeTable<B>& rope, const A* mods, const DitItems& items = {}) const {
    stream_front(ctx, cond, 0, rows.cond, modulated, src, modulated, qkv, cond_mods(mods).attn, rope, false, items);
  }

  // The streams' vectors in this block's table row [img 6D | cond 6D]: (attention, MLP) each.
  struct StreamMods {
    AdaLn<A> attn, mlp;
  };
  StreamMods img_mods(const A* row) const { return {AdaLn<A>::at(row, widths.hidden, 0), AdaLn<A>::at(row, widths.hidden, 3)}; }
  StreamMods cond_mods(const A* row) const { return img_mods(row + 6 * widths.hidden); }
  // This block's first norm of each stream, for the previous block to fuse into its last add.
  struct FirstNorms {
    AdaLn<A> img, cond;
  };
  FirstNorms first_norms(const A* row) const {
    return {AdaLn<A>::norm_at(row, widths.hidden), AdaLn<A>::norm_at(row + 6 * widths.hidden, widths.hidden)};
  }

  // The two streams touch disjoint rows until the joint attention: their products run paired
  // or on two queues (detail::StreamPair). `entry`: what the caller did already (the streams'
  // first modulated norms in s.modulated, the condition rows of s.qkv); next_img / next_cond:
  // (shift, scale) of the next block's first norm for each stream's rows (null: none);
  // cond_src: the condition rows' residual input when s.z does not hold it yet (the first
  // block; s.z gets the updated rows). Each gated residual add is fused with the modulated
  // norm after it. Called alone with the defaults it is the plain block; DitTrunk passes
  // `next` (and the rest) so that no norm runs as a pass of its own.
  void operator()(Context& ctx, SideQueue<B>& queue, DitScratch<B, A>& s, const JointRows& rows,
                  const RopeTable<B>& rope, const A* mods, DoubleBlockEntry entry = {}, const FirstNorms& next = {},
                  const A* cond_src = nullptr) const {
    using Pair = detail::StreamPair<B, W>;
    using Part = typename Pair::Part;
    using Stream = DoubleStream<B, W>;
    const std::int64_t D = widths.hidden, I = widths.attention_width();
    const float eps = widths.ln_eps;
    const bool paired = Pair::pairs(ctx, s, rows);
    EPONA_CHECK(!(paired && entry.cond_qkv), "DoubleStreamBlock: a condition front run ahead needs unpaired streams");
    const StreamMods mc = cond_mods(mods), mi = img_mods(mods);
    const DitItems& items = s.items;
    Pair pair(ctx, queue, paired, Part{&cond, 0, rows.cond, mc.attn, mc.mlp, next.cond, cond_src},
              Part{&img, rows.cond, rows.target, mi.attn, mi.mlp, next.img, nullptr}, items);
    const auto at = [](auto& t, const Part& p) { return t.data() + p.first * t.size(-1); };  // p's first row of t
    if (entry.cond_qkv) {
      // Only the target rows' front here; the join waits for the condition's on the side queue.
      stream_front(ctx, img, rows.cond, rows.target, s.z, nullptr, s.modulated, s.qkv.data(), mi.attn, rope,
                   entry.normed, items);
      queue.join(ctx);
    } else {
      pair.fork();
      if (!entry.normed)
        pair.each([&](Context& c, const Part& p) {
          detail::modulate_items(c, s.z, s.modulated, p.first, p.rows, p.attn, eps, items, p.src);
        });
      pair.linear(Stream::qkv_of, s.modulated, s.qkv);
      pair.join();
      detail::qk_norm_rope_items<B>(ctx, s.qkv.data(), widths, rope,
                                    std::array{detail::QkRows<B>(0, 0, rows.cond, cond.norm),
                                               detail::QkRows<B>(rows.cond, rows.cond, rows.total(), img.norm)},
                                    items);
    }
    detail::joint_attention<B>(ctx, s.qkv.data(), rows.total(), 0, rows.total(), widths, s.attn.data(), I, 3 * I,
                               items);
    pair.fork();
    pair.linear(Stream::proj_of, s.attn, s.sub);
    sum_partial(ctx, pair, s);
    pair.each([&](Context& c, const Part& p) {
      detail::add_gated_norm_items(c, p.src ? p.src : at(s.z, p), at(s.z, p), at(s.sub, p), p.attn.gate,
                                   at(s.modulated, p), p.rows, D, p.mlp, eps, items, p.src ? p.rows : items.rows);
    });
    pair.linear(Stream::fc1_of, s.modulated, s.mlp, img.mlp.fc1_epilogue());
    pair.linear(Stream::fc2_of, s.mlp, s.sub);
    sum_partial(ctx, pair, s);
    pair.each([&](Context& c, const Part& p) {
      detail::add_gated_norm_items(c, at(s.z, p), at(s.z, p), at(s.sub, p), p.mlp.gate, at(s.modulated, p), p.rows, D,
                                   p.next, eps, items, items.rows);
    });
    pair.join();
  }

  Flops flops(const JointRows& rows) const {
    return {img.mod.flops() + cond.mod.flops() + img.flops(rows.target) + cond.flops(rows.cond),
            detail::joint_attention_flops(widths, rows.total(), rows.total())};
  }

 private:
  // A shard's projections into the residual width (s.sub, both streams' rows of every item) summed
  // over its group, between the products and the residual adds of both streams.
  template <class Pair>
  void sum_partial(Context& ctx, Pair& pair, DitScratch<B, A>& s) const {
    if (widths.shards == 1) return;
    pair.join();
    detail::sum_over_shards(ctx, shard_sum, widths, s.sub.data(), s.items.count * s.items.rows * widths.hidden);
    pair.fork();
  }

  // One stream's first sublayer up to the attention over its rows [first, first + count) of
  // every item: the modulated norm of z's rows (or of src's) into `modulated` unless `normed`,
  // the qkv product into those rows of `qkv`, their QK RMSNorm + RoPE.
  void stream_front(Context& ctx, const DoubleStream<B, W>& st, std::int64_t first, std::int64_t count,
                    const Tensor<A, B>& z, const A* src, Tensor<A, B>& modulated, A* qkv, const AdaLn<A>& attn,
                    const RopeTable<B>& rope, bool normed, const DitItems& items) const {
    const std::int64_t D = widths.hidden, n = first + count;
    if (!normed) detail::modulate_items(ctx, z, modulated, first, count, attn, widths.ln_eps, items, src);
    detail::items_linear(st.qkv, ctx, modulated.data(), D, first, count, qkv, 3 * widths.attention_width(), first,
                         items, false);
    detail::qk_norm_rope_items<B>(ctx, qkv, widths, rope, std::array{detail::QkRows<B>(first, first, n, st.norm)},
                                  items);
  }
};

template <class B, class W>
struct SingleStreamBlock : Bindable<SingleStreamBlock<B, W>> {
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  DitWidths widths;
  Linear<B, W> linear1, linear2;  // (3I + Dm, D), (D, I + Dm); I = D and Dm the MLP width unless sharded
  QkNorm<B> norm;
  Modulation<B, W> modulation;
  Linear<B, W> q_part, kv_part, mlp_part;  // row views of linear1: [q | k v | mlp], set by bind
  const ShardSum<Context, A>* shard_sum = nullptr;  // the group's sum when widths.shards > 1

  SingleStreamBlock() = default;
  explicit SingleStreamBlock(const DitWidths& w)
      : widths(w), linear1(w.hidden, 3 * w.attention_width() + w.shard_mlp(), true),
        linear2(w.attention_width() + w.shard_mlp(), w.hidden, true), norm(w.head_dim(), w.rms_eps),
        modulation(w.hidden, 3) {}

  template <class V>
  void visit_params(const std::string& p, V& v) {
    linear1.visit_params(p + "linear1.", v);
    linear2.visit_params(p + "linear2.", v);
    norm.visit_params(p + "norm.", v);
    modulation.visit_params(p + "modulation.lin.", v);
    if (!linear1.weight.empty() && !linear1.bias.empty()) {
      const std::int64_t I = widths.attention_width();
      q_part = linear1.rows(0, I);
      kv_part = linear1.rows(I, 3 * I);
      mlp_part = linear1.rows(3 * I, 3 * I + widths.shard_mlp());
    }
  }

  // Modulation vectors of this block in a table row: (shift, scale, gate).
  std::int64_t modulation_width() const { return 3 * widths.hidden; }
  void modulations(Context& ctx, const A* silu_vecs, std::int64_t n, A* table, std::int64_t ld) const {
    modulation.rows(ctx, silu_vecs, n, table, ld);
  }
  // This block's norm, for the previous block to fuse into its last add.
  AdaLn<A> first_norm(const A* row) const { return AdaLn<A>::norm_at(row, widths.hidden); }

  // z ← z + gate ⊙ linear2([attention, GELU(mlp)]). Only the rows from `first_out` on are
  // updated (keys and values still come from every row): the last single block passes
  // rows.cond, since only the target tokens reach the final layer (docs/world-model.md,
  // design notes: exact pruning of the last blocks). `normed`: s.modulated holds the modulated
  // norm of every row already; `next`: the next block's norm over the updated rows, fused into
  // the gated residual add (DitTrunk passes both).
  void operator()(Context& ctx, SideQueue<B>& queue, DitScratch<B, A>& s, const JointRows& rows,
                  const RopeTable<B>& rope, const A* mods, std::int64_t first_out = 0, bool normed = false,
                  const AdaLn<A>& next = {}) const {
    const std::int64_t D = widths.hidden, I = widths.attention_width(), Dm = widths.shard_mlp(), n = rows.total(),
                       m = n - first_out;
    const DitItems& items = s.items;
    const std::int64_t R = items.rows;
    const AdaLn<A> mv = AdaLn<A>::at(mods, D);
    if (!normed) detail::modulate_items(ctx, s.z, s.modulated, 0, n, mv, widths.ln_eps, items);
    A* qkv = s.qkv.data();
    // Each item's cat rows 0..m = [attention | GELU(mlp)] of its updated rows: the MLP GEMM
    // writes its columns directly, the attention the others. Queries and then the MLP (rows from
    // first_out) run on the side queue, keys and values (all rows) on the main one; the main
    // queue waits for the queries only, so the QK-norm + RoPE (one pass for both) and the
    // attention overlap the MLP GEMM (disjoint columns of cat); linear2 waits for both.
    Context& side = queue.side(ctx);
    const auto product = [&](Context& c, const Linear<B, W>& l, const Tensor<A, B>& x, std::int64_t x_first,
                             std::int64_t rows_in, A* y, std::int64_t ldy, std::int64_t y_first,
                             typename Linear<B, W>::Epilogue epi = Linear<B, W>::Epilogue::None) {
      detail::items_linear(l, c, x.data(), x.size(-1), x_first, rows_in, y, ldy, y_first, items, true, epi);
    };
    queue.fork(ctx);
    product(side, q_part, s.modulated, first_out, m, qkv, 3 * I, first_out);
    product(ctx, kv_part, s.modulated, 0, n, qkv + I, 3 * I, 0);
    queue.join(ctx);
    product(side, mlp_part, s.modulated, first_out, m, s.cat.data() + I, I + Dm, 0, BackendEpilogue<B>::GeluTanh);
    detail::qk_norm_rope_items<B>(ctx, qkv, widths, rope, std::array{detail::QkRows<B>(0, first_out, n, norm)}, items);
    detail::joint_attention<B>(ctx, qkv, n, first_out, m, widths, s.cat.data(), I + Dm, 3 * I, items);
    queue.join(ctx);
    product(ctx, linear2, s.cat, 0, m, s.sub.data(), D, 0);
    detail::sum_over_shards(ctx, shard_sum, widths, s.sub.data(), ((items.count - 1) * R + m) * D);
    A* updated = s.z.data() + first_out * D;
    detail::add_gated_norm_items(ctx, updated, updated, s.sub.data(), mv.gate, s.modulated.data() + first_out * D, m, D,
                                 next, widths.ln_eps, items, R);
  }

  Flops flops(const JointRows& rows, std::int64_t first_out = 0) const {
    const std::int64_t n = rows.total(), m = n - first_out;
    return {modulation.flops() + kv_part.flops(n) + q_part.flops(m) + mlp_part.flops(m) + linear2.flops(m),
            detail::joint_attention_flops(widths, m, n)};
  }
};

template <class B, class W>
struct LastLayer : Bindable<LastLayer<B, W>> {
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  DitWidths widths;
  Modulation<B, W> adaLN_modulation;  // "adaLN_modulation.1." (index 0 is the SiLU)
  Linear<B, W> linear;

  LastLayer() = default;
  LastLayer(const DitWidths& w, std::int64_t out_channels)
      : widths(w), adaLN_modulation(w.hidden, 2), linear(w.hidden, out_channels, true) {}

  template <class V>
  void visit_params(const std::string& p, V& v) {
    adaLN_modulation.visit_params(p + "adaLN_modulation.1.", v);
    linear.visit_params(p + "linear.", v);
  }

  // out (target, out_channels) = linear((1 + scale)·LN(z_target) + shift); (shift, scale) halves.
  // Modulation vectors in a table row: (shift, scale).
  std::int64_t modulation_width() const { return 2 * widths.hidden; }
  void modulations(Context& ctx, const A* silu_vecs, std::int64_t n, A* table, std::int64_t ld) const {
    adaLN_modulation.rows(ctx, silu_vecs, n, table, ld);
  }
  AdaLn<A> first_norm(const A* row) const { return AdaLn<A>::norm_at(row, widths.hidden); }

  // `normed`: the previous block's last residual add wrote the target rows' modulated norm.
  void operator()(Context& ctx, DitScratch<B, A>& s, const JointRows& rows, const A* mods, Tensor<A, B>& out,
                  bool normed = false) const {
    const DitItems& items = s.items;
    if (!normed)
      detail::modulate_items(ctx, s.z, s.modulated, rows.cond, rows.target, first_norm(mods), widths.ln_eps, items);
    EPONA_CHECK(out.numel() == items.count * rows.target * linear.out, "DiT final layer: output of ",
                shape_str(out.shape()), " for ", items.count, " items of ", rows.target, " x ", linear.out);
    const std::int64_t D = widths.hidden, C = linear.out;
    linear.items(ctx, s.modulated.data() + rows.cond * D, D, items.rows * D, rows.target, out.data(), C,
                 rows.target * C, items.count);
  }

  Flops flops(const JointRows& rows) const { return {adaLN_modulation.flops() + linear.flops(rows.target), 0}; }
};

}  // namespace epona::nn
