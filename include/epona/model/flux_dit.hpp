// epona/model/flux_dit.hpp — Epona's two DiTs as one template: the VisDiT (models/flux_dit.py
// `FluxDiT`, prefix `module.dit.`, with `vector_in` for the action embedding) and the TrajDiT
// (models/traj_dit.py `TrajDiT`, prefix `module.traj_dit.`, input layer `traj_in`, no
// `vector_in`). forward(x, ids, cond, cond_ids, t, y) -> velocity, plus the rectified-flow
// sampler; the step-invariant work (cond_in, vector_in, RoPE table, time embeddings) is
// prepared once per sample.
#pragma once

#include <cstdint>
#include <cstring>
#include <optional>
#include <string>
#include <vector>

#include "epona/core/arena.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/flow/euler.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config.hpp"
#include "epona/model/dit_blocks.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/embeddings.hpp"
#include "epona/nn/linear.hpp"
#include "epona/nn/mlp.hpp"
#include "epona/nn/rope.hpp"

namespace epona::model {

struct FluxDitConfig {
  std::int64_t in_channels = 32, out_channels = 32, context_in_dim = 2048;
  std::int64_t hidden_size = 2048, num_heads = 16, depth = 6, depth_single_blocks = 6;
  std::int64_t vec_in_dim = 0;  // 0: no vector_in (the TrajDiT)
  std::int64_t mlp_ratio = constants::dit_mlp_ratio;
  std::vector<std::int64_t> axes_dim = {16, 56, 56};
  double theta = constants::dit_rope_theta;
  std::string input_name = "img_in";  // "traj_in" for the TrajDiT
  std::int64_t time_dim = constants::timestep_embed_dim;
  double time_max_period = constants::timestep_max_period;
  float time_factor = static_cast<float>(constants::timestep_time_factor);

  static FluxDitConfig vis(const WorldModelConfig& c) {
    FluxDitConfig d;
    d.in_channels = d.out_channels = c.token_dim();
    d.context_in_dim = c.context_in_dim();
    d.hidden_size = c.n_embd_dit;
    d.num_heads = c.n_head_dit;
    d.depth = c.vis_double_blocks();
    d.depth_single_blocks = c.vis_single_blocks();
    d.vec_in_dim = c.vis_vec_in_dim();
    d.axes_dim.assign(c.axes_dim_dit.begin(), c.axes_dim_dit.end());
    return d;
  }
  static FluxDitConfig traj(const WorldModelConfig& c) {
    FluxDitConfig d;
    d.in_channels = d.out_channels = constants::traj_token_size;
    d.context_in_dim = c.context_in_dim();
    d.hidden_size = c.n_embd_dit_traj;
    d.num_heads = c.n_head_dit_traj;
    d.depth = c.traj_double_blocks();
    d.depth_single_blocks = c.traj_single_blocks();
    d.vec_in_dim = 0;
    d.axes_dim.assign(c.axes_dim_dit_traj.begin(), c.axes_dim_dit_traj.end());
    d.input_name = "traj_in";
    return d;
  }
  DitWidths widths() const { return {hidden_size, num_heads, mlp_ratio * hidden_size}; }
};

template <class B, class W>
class FluxDiT {
 public:
  using Context = BackendContext<B>;

  // What stays the same over the steps of one sample: cond_in(cond), vector_in(y) and the
  // RoPE table of the joint ids, for every batch item.
  struct Conditioning {
    std::int64_t batch = 0;
    JointRows rows;
    Tensor<float, B> cond;   // (batch, Lc, D) = cond_in(cond)
    Tensor<float, B> vec_y;  // (batch, D) = vector_in(y), empty without vector_in
    Tensor<float, B> vec_y_hidden;  // (batch, D) vector_in's hidden layer
    nn::RopeTable<B> rope;   // (batch·(Lc+Lx), head_dim/2)
  };

  FluxDiT() = default;
  explicit FluxDiT(const FluxDitConfig& c)
      : cfg_(c), widths_(c.widths()), input_(c.in_channels, c.hidden_size, true),
        time_in_(c.time_dim, c.hidden_size), cond_in_(c.context_in_dim, c.hidden_size, true),
        final_layer_(widths_, c.out_channels) {
    EPONA_CHECK(c.num_heads > 0 && c.hidden_size % c.num_heads == 0, "DiT: num_heads ", c.num_heads,
                " does not divide hidden_size ", c.hidden_size);
    std::int64_t axes = 0;
    for (auto a : c.axes_dim) axes += a;
    EPONA_CHECK(axes == widths_.head_dim(), "DiT: axes_dim sums to ", axes, ", the head dim is ", widths_.head_dim());
    if (c.vec_in_dim > 0) vector_in_.emplace(c.vec_in_dim, c.hidden_size);
    for (std::int64_t i = 0; i < c.depth; ++i) double_blocks_.emplace_back(widths_);
    for (std::int64_t i = 0; i < c.depth_single_blocks; ++i) single_blocks_.emplace_back(widths_);
  }

  const FluxDitConfig& config() const { return cfg_; }

  void bind(const io::TensorMap& w, const std::string& prefix, io::BindReport& r) {
    input_.bind(w, prefix + cfg_.input_name + ".", r);
    time_in_.bind(w, prefix + "time_in.", r);
    if (vector_in_) vector_in_->bind(w, prefix + "vector_in.", r);
    cond_in_.bind(w, prefix + "cond_in.", r);
    for (std::size_t i = 0; i < double_blocks_.size(); ++i)
      double_blocks_[i].bind(w, prefix + "double_blocks." + std::to_string(i) + ".", r);
    for (std::size_t i = 0; i < single_blocks_.size(); ++i)
      single_blocks_[i].bind(w, prefix + "single_blocks." + std::to_string(i) + ".", r);
    final_layer_.bind(w, prefix + "final_layer.", r);
  }

  // ---- workspace sizes (bytes of arena) ----
  std::size_t conditioning_bytes(std::int64_t batch, const JointRows& rows) const {
    ArenaCounter<B> c;
    plan_conditioning(c, batch, rows);
    return c.bytes();
  }
  std::size_t velocity_bytes(const JointRows& rows) const {
    ArenaCounter<B> c;
    DitScratch<B>::plan(c, rows.total(), widths_);
    return c.bytes();
  }
  // Everything sample() takes on top of its conditioning.
  std::size_t sample_bytes(std::int64_t batch, const JointRows& rows, std::int64_t steps) const {
    ArenaCounter<B> c;
    plan_sampler(c, batch, rows, steps);
    return c.bytes() + velocity_bytes(rows);
  }
  // Everything forward() takes.
  std::size_t forward_bytes(std::int64_t batch, const JointRows& rows) const {
    ArenaCounter<B> c;
    c.template take<float>({batch, cfg_.time_dim});
    return conditioning_bytes(batch, rows) + c.bytes() + velocity_bytes(rows);
  }

  // cond (batch, Lc, context) and y (batch, vec_in_dim) backend; ids host (batch, L·, n_axes).
  Conditioning prepare(Context& ctx, Arena<B>& arena, const Tensor<float, B>& cond, const Tensor<float, Cpu>& cond_ids,
                       const Tensor<float, Cpu>& target_ids, const Tensor<float, B>& y) const {
    EPONA_CHECK(cond.dim() == 3 && cond.size(2) == cfg_.context_in_dim, "DiT condition must be (B, L, ",
                cfg_.context_in_dim, "), got ", shape_str(cond.shape()));
    const std::int64_t batch = cond.size(0);
    EPONA_CHECK(target_ids.dim() == 3, "DiT target ids must be (B, L, axes), got ", shape_str(target_ids.shape()));
    const JointRows rows{cond.size(1), target_ids.size(1)};
    const auto axes = static_cast<std::int64_t>(cfg_.axes_dim.size());
    check_shape(cond_ids, {batch, rows.cond, axes}, "DiT condition ids");
    check_shape(target_ids, {batch, rows.target, axes}, "DiT target ids");
    if (vector_in_) check_shape(y, {batch, cfg_.vec_in_dim}, "DiT vector input y");
    Conditioning c = plan_conditioning(arena, batch, rows);
    cond_in_(ctx, cond, c.cond);
    if (vector_in_) (*vector_in_)(ctx, y, c.vec_y_hidden, c.vec_y);
    const auto host = nn::nd_rope_table(joint_ids(cond_ids, target_ids), cfg_.axes_dim, cfg_.theta);
    BackendTraits<B>::upload_into(ctx, host.cos, c.rope.cos);
    BackendTraits<B>::upload_into(ctx, host.sin, c.rope.sin);
    return c;
  }

  // v = DiT(x, t) for every batch item. x (batch, Lx, in); temb (batch or 1, time_dim) =
  // timestep_embedding(t); out (batch, Lx, out).
  void velocity(Context& ctx, Arena<B>& arena, const Conditioning& c, const Tensor<float, B>& x,
                const Tensor<float, B>& temb, Tensor<float, B>& out) const {
    check_shape(x, {c.batch, c.rows.target, cfg_.in_channels}, "DiT input x");
    check_shape(out, {c.batch, c.rows.target, cfg_.out_channels}, "DiT velocity output");
    EPONA_CHECK(temb.dim() == 2 && temb.size(1) == cfg_.time_dim && (temb.size(0) == 1 || temb.size(0) == c.batch),
                "DiT time embedding must be (1 or B, ", cfg_.time_dim, "), got ", shape_str(temb.shape()));
    const std::int64_t n = c.rows.total();
    for (std::int64_t b = 0; b < c.batch; ++b) {
      ArenaScope<B> scope(arena);
      auto s = DitScratch<B>::plan(arena, n, widths_);
      embed_inputs(ctx, s, c, b, x[b], temb.size(0) == 1 ? temb : temb.slice(b, b + 1));
      const nn::RopeTable<B> rope{c.rope.cos.slice(b * n, (b + 1) * n), c.rope.sin.slice(b * n, (b + 1) * n)};
      for (const auto& block : double_blocks_) block(ctx, s, c.rows, rope);
      for (std::size_t j = 0; j < single_blocks_.size(); ++j)
        single_blocks_[j](ctx, s, c.rows, rope, first_updated_row(j, c.rows));
      auto o = out[b];
      final_layer_(ctx, s, c.rows, o);
    }
  }

  // The official forward(x, ids, cond, cond_ids, t, y) in one call; t (batch) on the host.
  void forward(Context& ctx, Arena<B>& arena, const Tensor<float, B>& x, const Tensor<float, Cpu>& x_ids,
               const Tensor<float, B>& cond, const Tensor<float, Cpu>& cond_ids, const Tensor<float, Cpu>& t,
               const Tensor<float, B>& y, Tensor<float, B>& out) const {
    ArenaScope<B> scope(arena);
    const Conditioning c = prepare(ctx, arena, cond, cond_ids, x_ids, y);
    check_shape(t, {c.batch}, "DiT timesteps t");
    auto temb = arena.template take<float>({c.batch, cfg_.time_dim});
    upload_time_embedding(ctx, t.data(), c.batch, temb);
    velocity(ctx, arena, c, x, temb, out);
  }

  // Euler sampling from the noise in x (batch, Lx, in) to the sample, in place, over `grid`.
  void sample(Context& ctx, Arena<B>& arena, const Conditioning& c, const std::vector<float>& grid,
              Tensor<float, B>& x) const {
    EPONA_CHECK(cfg_.in_channels == cfg_.out_channels, "DiT sampling needs in_channels == out_channels");
    const flow::RectifiedFlowEuler<B> euler(grid);
    ArenaScope<B> scope(arena);
    auto [temb, v] = plan_sampler(arena, c.batch, c.rows, euler.steps());
    upload_time_embedding(ctx, grid.data(), euler.steps(), temb);  // t_0 .. t_{N-1}
    euler.sample(ctx, x, v, [&](std::int64_t i, float, const Tensor<float, B>& state, Tensor<float, B>& vel) {
      velocity(ctx, arena, c, state, temb.slice(i, i + 1), vel);
    });
  }

  // FLOPs of one velocity evaluation including cond_in, batch 1: `executed` counts what runs
  // (the last single block updates only the target rows); otherwise the official count of
  // compute-budget.md §3.2/3.3 (every row of every block).
  nn::Flops forward_flops(const JointRows& rows, bool executed = true) const {
    nn::Flops f{input_.flops(rows.target) + time_in_.flops(1) + cond_in_.flops(rows.cond), 0};
    if (vector_in_) f.gemm += vector_in_->flops(1);
    for (const auto& b : double_blocks_) f += b.flops(rows);
    for (std::size_t j = 0; j < single_blocks_.size(); ++j)
      f += single_blocks_[j].flops(rows, executed ? first_updated_row(j, rows) : 0);
    return f + final_layer_.flops(rows);
  }

 private:
  // The last single block only needs to update the target rows (the final layer reads no others).
  std::int64_t first_updated_row(std::size_t single_index, const JointRows& rows) const {
    return single_index + 1 == single_blocks_.size() ? rows.cond : 0;
  }

  template <class Alloc>
  Conditioning plan_conditioning(Alloc& a, std::int64_t batch, const JointRows& rows) const {
    const std::int64_t pairs = widths_.head_dim() / 2;
    Conditioning c;
    c.batch = batch;
    c.rows = rows;
    c.cond = a.template take<float>({batch, rows.cond, cfg_.hidden_size});
    if (vector_in_) {
      c.vec_y = a.template take<float>({batch, cfg_.hidden_size});
      c.vec_y_hidden = a.template take<float>({batch, cfg_.hidden_size});
    }
    c.rope.cos = a.template take<float>({batch * rows.total(), pairs});
    c.rope.sin = a.template take<float>({batch * rows.total(), pairs});
    return c;
  }
  template <class Alloc>
  std::pair<Tensor<float, B>, Tensor<float, B>> plan_sampler(Alloc& a, std::int64_t batch, const JointRows& rows,
                                                             std::int64_t steps) const {
    auto temb = a.template take<float>({steps, cfg_.time_dim});
    auto v = a.template take<float>({batch, rows.target, cfg_.out_channels});
    return {temb, v};
  }

  static Tensor<float, Cpu> joint_ids(const Tensor<float, Cpu>& cond_ids, const Tensor<float, Cpu>& target_ids) {
    const std::int64_t batch = cond_ids.size(0), lc = cond_ids.size(1), lx = target_ids.size(1), k = cond_ids.size(2);
    Tensor<float, Cpu> ids({batch * (lc + lx), k});
    for (std::int64_t b = 0; b < batch; ++b) {
      std::memcpy(ids[b * (lc + lx)].data(), cond_ids[b].data(), sizeof(float) * lc * k);
      std::memcpy(ids[b * (lc + lx) + lc].data(), target_ids[b].data(), sizeof(float) * lx * k);
    }
    return ids;
  }

  void upload_time_embedding(Context& ctx, const float* t, std::int64_t n, Tensor<float, B>& dst) const {
    Tensor<float, Cpu> host({n, cfg_.time_dim});
    nn::timestep_embedding(t, n, cfg_.time_dim, cfg_.time_max_period, cfg_.time_factor, host.data());
    BackendTraits<B>::upload_into(ctx, host, dst);
  }

  // z = [cond_in(cond) | input(x)], vec = time_in(temb) (+ vector_in(y)), silu_vec = SiLU(vec).
  void embed_inputs(Context& ctx, DitScratch<B>& s, const Conditioning& c, std::int64_t b, const Tensor<float, B>& x,
                    const Tensor<float, B>& temb) const {
    auto target = s.z.slice(c.rows.cond, c.rows.total());
    input_(ctx, x, target);
    copy(ctx, c.cond[b].data(), s.z.data(), c.rows.cond * cfg_.hidden_size);
    time_in_(ctx, temb, s.vec_hidden, s.vec);
    if (vector_in_) add_inplace(ctx, s.vec.data(), c.vec_y[b].data(), cfg_.hidden_size);
    silu_to(ctx, s.vec.data(), s.silu_vec.data(), cfg_.hidden_size);
  }

  FluxDitConfig cfg_;
  DitWidths widths_;
  nn::Linear<B, W> input_;  // img_in / traj_in
  nn::MlpEmbedder<B, W> time_in_;
  std::optional<nn::MlpEmbedder<B, W>> vector_in_;
  nn::Linear<B, W> cond_in_;
  std::vector<DoubleStreamBlock<B, W>> double_blocks_;
  std::vector<SingleStreamBlock<B, W>> single_blocks_;
  LastLayer<B, W> final_layer_;
};

}  // namespace epona::model
