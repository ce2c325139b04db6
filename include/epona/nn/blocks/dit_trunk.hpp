// epona/nn/blocks/dit_trunk.hpp — the body of a FLUX-style DiT (Epona's VisDiT and TrajDiT, or a
// DiT of one's own): double-stream blocks, then single-stream blocks, then the final layer, over
// one residual table z = [condition rows | target rows] (nn/blocks/dit_blocks.hpp). The trunk owns
// the fusions between its blocks, so calling it is the fast path: each block's last residual add
// also writes the next block's first modulated norm, the last single block updates only the
// target rows (they alone reach the final layer), and the first double block reads the condition
// rows from where they lie (no copy into z). Every block's adaLN vectors for one conditioning
// vector are one row of a table (modulations()), computed once per timestep, not per token.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/nn/blocks/dit_blocks.hpp"
#include "epona/nn/linear_shards.hpp"
#include "epona/nn/flops.hpp"
#include "epona/nn/modulation.hpp"
#include "epona/nn/parameter.hpp"
#include "epona/nn/rope.hpp"

namespace epona::nn {

// Where a trunk evaluation finds its condition rows (both optional).
template <class B, class A>
struct TrunkInputs {
  // The condition rows' residual input when s.z does not hold them (e.g. a step-invariant
  // projection of the condition): the first block reads them here and writes the update into s.z.
  const A* cond = nullptr;
  // A qkv table whose condition rows the first double block's condition_front() filled ahead
  // (the samplers' pipelined front; unpaired streams only). Empty: none.
  Tensor<A, B> cond_qkv;
};

template <class B, class W>
class DitTrunk : public Bindable<DitTrunk<B, W>> {
 public:
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  using Scratch = DitScratch<B, A>;

  DitTrunk() = default;
  // `double_blocks` double-stream and `single_blocks` single-stream blocks of `widths`, and a
  // final layer projecting the target rows to `out_channels`.
  DitTrunk(const DitWidths& widths, std::int64_t double_blocks, std::int64_t single_blocks, std::int64_t out_channels)
      : widths_(widths), final_(widths, out_channels) {
    EPONA_CHECK(widths.heads > 0 && widths.hidden % widths.heads == 0 && double_blocks >= 0 && single_blocks >= 0,
                "DiT trunk: heads ", widths.heads, " must be positive and divide hidden ", widths.hidden, ", blocks ",
                double_blocks, " + ", single_blocks, " must not be negative");
    EPONA_CHECK(widths.shards >= 1 && widths.heads % widths.shards == 0 && widths.mlp_hidden % widths.shards == 0,
                "DiT trunk: ", widths.shards, " shards must divide the ", widths.heads, " heads and the MLP width ",
                widths.mlp_hidden);
    for (std::int64_t i = 0; i < double_blocks; ++i) doubles_.emplace_back(widths);
    for (std::int64_t i = 0; i < single_blocks; ++i) singles_.emplace_back(widths);
  }

  // The official names under the DiT's prefix: double_blocks.i., single_blocks.j., final_layer.
  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    for (std::size_t i = 0; i < doubles_.size(); ++i)
      doubles_[i].visit_params(prefix + "double_blocks." + std::to_string(i) + ".", v);
    for (std::size_t i = 0; i < singles_.size(); ++i)
      singles_[i].visit_params(prefix + "single_blocks." + std::to_string(i) + ".", v);
    final_.visit_params(prefix + "final_layer.", v);
  }

  const DitWidths& widths() const { return widths_; }
  const std::vector<DoubleStreamBlock<B, W>>& double_blocks() const { return doubles_; }
  const std::vector<SingleStreamBlock<B, W>>& single_blocks() const { return singles_; }
  const LastLayer<B, W>& final_layer() const { return final_; }
  std::int64_t out_channels() const { return final_.linear.out; }
  bool has_double_blocks() const { return !doubles_.empty(); }

  // The tensor-parallel group's sum of this shard's partial outputs (widths().shards > 1); it must
  // outlive the trunk's use. Copies of the trunk keep the pointer.
  void set_shard_sum(const ShardSum<Context, A>* sum) {
    EPONA_CHECK(!sum || sum->size() == widths_.shards, "DiT trunk: a group of ", sum ? sum->size() : 0,
                " shards for a trunk sharded ", widths_.shards, " ways");
    for (auto& b : doubles_) b.shard_sum = sum;
    for (auto& b : singles_) b.shard_sum = sum;
  }

  // How the whole model's weights (under `prefix`) split into this trunk's shard: each block's
  // products out of the residual width (qkv, MLP in) take their heads' and columns' rows; those
  // into it (attention out, MLP out) the same columns, with the bias on shard 0 alone (it is
  // added once, after the sum). Everything else (modulations, norms, the final layer) is whole.
  std::vector<LinearSplit> shard_splits(const std::string& prefix) const {
    const std::int64_t D = widths_.hidden, Dm = widths_.mlp_hidden;
    std::vector<LinearSplit> s;
    for (std::size_t i = 0; i < doubles_.size(); ++i)
      for (const char* stream : {"img", "cond"}) {
        const std::string p = prefix + "double_blocks." + std::to_string(i) + "." + stream;
        s.push_back({p + "_attn.qkv.", LinearSplit::outputs, {D, D, D}});
        s.push_back({p + "_attn.proj.", LinearSplit::inputs, {D}});
        s.push_back({p + "_mlp.0.", LinearSplit::outputs, {Dm}});
        s.push_back({p + "_mlp.2.", LinearSplit::inputs, {Dm}});
      }
    for (std::size_t j = 0; j < singles_.size(); ++j) {
      const std::string p = prefix + "single_blocks." + std::to_string(j) + ".";
      s.push_back({p + "linear1.", LinearSplit::outputs, {D, D, D, Dm}});
      s.push_back({p + "linear2.", LinearSplit::inputs, {D, Dm}});
    }
    return s;
  }

  // Width of one modulation table row: [double 0: img 6D, cond 6D | ... | single 0: 3D | ... |
  // final layer 2D].
  std::int64_t modulation_width() const {
    std::int64_t w = final_.modulation_width();
    for (const auto& b : doubles_) w += b.modulation_width();
    for (const auto& b : singles_) w += b.modulation_width();
    return w;
  }
  // Table rows for n vectors: silu_vecs (n, D) = SiLU(conditioning vector), rows of `table` ld
  // apart (each block's Linear is one GEMM over the n rows).
  void modulations(Context& ctx, const A* silu_vecs, std::int64_t n, A* table, std::int64_t ld) const {
    std::int64_t offset = 0;
    const auto fill = [&](const auto& block) {
      block.modulations(ctx, silu_vecs, n, table + offset, ld);
      offset += block.modulation_width();
    };
    for (const auto& b : doubles_) fill(b);
    for (const auto& b : singles_) fill(b);
    fill(final_);
  }

  // The block scratch of one evaluation of `items` batch items over `rows` each (z and the
  // buffers the blocks share); the caller sets the items' modulation and RoPE strides.
  template <class Alloc>
  Scratch plan_scratch(Alloc& a, const JointRows& rows, std::int64_t items = 1) const {
    return Scratch::plan(a, rows, widths_, items);
  }

  // out (items, target, out_channels) = the trunk over z, with the vectors of table row `mods`
  // (item 0's; s.items says where the others' lie). Each item's target rows of s.z hold its
  // embedded target tokens, its condition rows the embedded condition unless `in.cond` points at
  // them ((items, cond, D), contiguous). s is clobbered.
  void operator()(Context& ctx, Scratch& s, const JointRows& rows, const RopeTable<B>& rope, const A* mods,
                  Tensor<A, B>& out, const TrunkInputs<B, A>& in = {}) const {
    const std::int64_t D = widths_.hidden;
    for (std::int64_t b = 0; doubles_.empty() && in.cond && b < s.items.count; ++b)
      copy(ctx, in.cond + b * rows.cond * D, s.z.data() + b * s.items.rows * D, rows.cond * D);
    for (std::size_t j = 0; j < doubles_.size(); ++j) {
      const A* next = mods + doubles_[j].modulation_width();
      const bool ahead = j == 0 && !in.cond_qkv.empty();
      Scratch sj = s;
      if (ahead) sj.qkv = in.cond_qkv;
      doubles_[j](ctx, side_, sj, rows, rope, mods, DoubleBlockEntry{j > 0, ahead}, first_norms_after_double(j, next),
                  j == 0 ? in.cond : nullptr);
      mods = next;
    }
    for (std::size_t j = 0; j < singles_.size(); ++j) {
      const A* next = mods + singles_[j].modulation_width();
      const AdaLn<A> next_norm = j + 1 < singles_.size() ? singles_[j + 1].first_norm(next) : final_.first_norm(next);
      singles_[j](ctx, side_, s, rows, rope, mods, first_updated_row(j, rows), j > 0 || !doubles_.empty(), next_norm);
      mods = next;
    }
    final_(ctx, s, rows, mods, out, !doubles_.empty() || !singles_.empty());
  }

  // The first double block's condition stream up to its attention, for a caller that runs it
  // ahead on the side queue (TrunkInputs::cond_qkv); see DoubleStreamBlock::condition_front.
  void condition_front(Context& ctx, const A* src, Tensor<A, B>& modulated, A* qkv, const JointRows& rows,
                       const RopeTable<B>& rope, const A* mods, const DitItems& items = {}) const {
    doubles_.front().condition_front(ctx, src, modulated, qkv, rows, rope, mods, items);
  }
  // The blocks' second queue (a second CUDA stream; the CPU runs in order).
  SideQueue<B>& queue() const { return side_; }

  // FLOPs of one evaluation: `executed` counts what runs (the last single block updates only the
  // target rows); otherwise what the official code computes (every row of every block).
  Flops flops(const JointRows& rows, bool executed = true) const {
    Flops f{0, 0};
    for (const auto& b : doubles_) f += b.flops(rows);
    for (std::size_t j = 0; j < singles_.size(); ++j) f += singles_[j].flops(rows, executed ? first_updated_row(j, rows) : 0);
    return f + final_.flops(rows);
  }

 private:
  // The last single block updates only the target rows.
  std::int64_t first_updated_row(std::size_t single_index, const JointRows& rows) const {
    return single_index + 1 == singles_.size() ? rows.cond : 0;
  }
  // The norm after double block j, per stream: the next double block's own per-stream norms, or
  // the one norm of the single block or final layer after it, on both streams' rows.
  typename DoubleStreamBlock<B, W>::FirstNorms first_norms_after_double(std::size_t j, const A* next) const {
    if (j + 1 < doubles_.size()) return doubles_[j + 1].first_norms(next);
    const AdaLn<A> n = singles_.empty() ? final_.first_norm(next) : singles_.front().first_norm(next);
    return {n, n};
  }

  DitWidths widths_;
  std::vector<DoubleStreamBlock<B, W>> doubles_;
  std::vector<SingleStreamBlock<B, W>> singles_;
  LastLayer<B, W> final_;
  mutable SideQueue<B> side_;
};

}  // namespace epona::nn
