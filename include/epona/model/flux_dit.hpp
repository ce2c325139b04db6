// epona/model/flux_dit.hpp — Epona's two DiTs as one template: the VisDiT (models/flux_dit.py
// `FluxDiT`, prefix `module.dit.`, with `vector_in` for the action embedding) and the TrajDiT
// (models/traj_dit.py `TrajDiT`, prefix `module.traj_dit.`, input layer `traj_in`, no
// `vector_in`). forward(x, ids, cond, cond_ids, t, y) -> velocity, plus the rectified-flow
// sampler. Step-invariant work is hoisted out of the sampling loop (docs/world-model.md): cond_in,
// vector_in and the RoPE table once per sample, and every block's modulation for all steps at
// once (time_in and the modulation Linears as GEMMs over the steps); the loop itself is replayed
// as one CUDA graph on the GPU, and with unpaired streams (the TrajDiT) each step's first
// condition-stream work runs ahead, beside the previous step's few-row tail (SamplerOptions).
#pragma once

#include <algorithm>
#include <bit>
#include <cstdint>
#include <cstring>
#include <optional>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/core/arena.hpp"
#include "epona/core/env.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/blocks/dit_trunk.hpp"
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
  // One shard of a tensor-parallel group (docs/parallel.md): the trunk's heads and MLP columns
  // split over `shard.size`; bind it to shard_weights() of the whole model's map.
  TensorShard shard;

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
  nn::DitWidths widths() const {
    nn::DitWidths w{hidden_size, num_heads, mlp_ratio * hidden_size};
    w.shards = shard.size;
    return w;
  }
};

template <class B, class W>
class FluxDiT : public nn::Bindable<FluxDiT<B, W>> {
 public:
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  static constexpr bool kConvertInputs = !std::is_same_v<A, float>;  // float32 inputs need a cast

  // What stays the same over the steps of one sample: cond_in(cond), vector_in(y) and the
  // RoPE table of the joint ids, for every batch item.
  struct Conditioning {
    std::int64_t batch = 0;
    nn::JointRows rows;
    Tensor<A, B> cond;      // (batch, Lc, D) = cond_in(cond)
    Tensor<A, B> vec_y;     // (batch, D) = vector_in(y), empty without vector_in
    nn::RopeTable<B> rope;  // (batch·(Lc+Lx), head_dim/2): each item's rows, or only item 0's when shared
    bool shared_rope = false;  // every item has the same ids (the world model's): one table serves all
  };

  // Every block's modulation vectors for `times` timesteps of each batch item: row b·times + i
  // of the table is [double 0: img 6D, cond 6D | ... | single 0: 3D | ... | final layer 2D].
  struct Modulations {
    std::int64_t times = 0, width = 0;
    bool shared = false;  // one row per time for every item (a sample without vector_in)
    Tensor<A, B> table;   // (batch·times, width), or (times, width) when shared
    const A* row(std::int64_t b, std::int64_t i) const { return table.data() + ((shared ? 0 : b) * times + i) * width; }
  };

  // How sample() runs the steps (it changes no result bit, and benchmarks compare both). It
  // applies where the model's shapes allow it.
  struct SamplerOptions {
    // With unpaired streams (the TrajDiT's 515 / 15 rows), step i + 1's condition front of the
    // first double block (modulated norm, qkv, QK-norm + RoPE: step-invariant but for its
    // modulation) runs on the side queue during step i's few-row tail.
    bool pipelined_condition = true;

    // Every model's starting options: the defaults, unless EPONA_DIT_PIPELINE=0 (read once per
    // process, here only).
    static SamplerOptions from_environment() {
      static const SamplerOptions read{env_flag("EPONA_DIT_PIPELINE", true)};
      return read;
    }
  };

  FluxDiT() = default;
  explicit FluxDiT(const FluxDitConfig& c)
      : cfg_(c), input_(c.in_channels, c.hidden_size, true), time_in_(c.time_dim, c.hidden_size),
        cond_in_(c.context_in_dim, c.hidden_size, true),
        trunk_(c.widths(), c.depth, c.depth_single_blocks, c.out_channels) {
    // The trunk has refused heads that do not divide the width.
    std::int64_t axes = 0;
    for (auto a : c.axes_dim) axes += a;
    const std::int64_t head_dim = trunk_.widths().head_dim();
    EPONA_CHECK(axes == head_dim, "DiT: axes_dim sums to ", axes, ", the head dim is ", head_dim);
    c.shard.check("DiT");
    if (c.vec_in_dim > 0) vector_in_.emplace(c.vec_in_dim, c.hidden_size);
  }

  const FluxDitConfig& config() const { return cfg_; }

  // Tensor parallelism (config().shard): this shard's weights cut from the whole model's map
  // (names under `prefix`), and the group's sum of its partial outputs, which must outlive the
  // model's use. Everything else runs as in a whole model, on every shard alike.
  io::TensorMap shard_weights(const io::TensorMap& full, const std::string& prefix) const {
    return nn::shard_weights(full, trunk_.shard_splits(prefix), cfg_.shard);
  }
  void set_shard_sum(const ShardSum<Context, A>* sum) {
    trunk_.set_shard_sum(sum);
    reset_sampler_graph();
  }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    input_.visit_params(prefix + cfg_.input_name + ".", v);
    time_in_.visit_params(prefix + "time_in.", v);
    if (vector_in_) vector_in_->visit_params(prefix + "vector_in.", v);
    cond_in_.visit_params(prefix + "cond_in.", v);
    trunk_.visit_params(prefix, v);
  }

  // ---- workspace sizes (bytes of arena) ----
  // What prepare() takes at most (its Conditioning stays, its scratch is released).
  std::size_t conditioning_bytes(std::int64_t batch, const nn::JointRows& rows) const {
    return conditioning_sizes(batch, rows).total();
  }
  // Items folded into one pass through the blocks at most: a larger batch runs in passes of this
  // many (the scratch grows with the items: 64 VisDiT items take ~4 GiB of bf16 scratch).
  static constexpr std::int64_t kMaxFoldedItems = 64;
  static std::int64_t folded_items(std::int64_t batch) { return std::min(batch, kMaxFoldedItems); }

  // One velocity evaluation of `batch` items (folded into passes through the blocks).
  std::size_t velocity_bytes(std::int64_t batch, const nn::JointRows& rows) const {
    ArenaCounter<B> c;
    plan_velocity(c, folded_items(batch), rows);
    return c.bytes();
  }
  // Everything sample() takes on top of its conditioning, for `steps` steps of `solver`.
  std::size_t sample_bytes(std::int64_t batch, const nn::JointRows& rows, std::int64_t steps,
                           flow::SolverKind solver = flow::SolverKind::euler) const {
    ArenaCounter<B> v;
    v.template take<A>({batch, rows.target, cfg_.out_channels});
    if (kConvertInputs) v.template take<A>({batch, rows.target, cfg_.in_channels});
    plan_front(v, batch, rows);
    for (int j = 0; j < flow::solver_scratch_states(solver); ++j) v.template take<float>({batch, rows.target, cfg_.in_channels});
    const auto m = modulation_sizes(modulation_rows(batch), flow::solver_evaluations(solver, steps));
    return m.kept + std::max(m.scratch, v.bytes() + velocity_bytes(batch, rows));
  }
  // Everything forward() takes.
  std::size_t forward_bytes(std::int64_t batch, const nn::JointRows& rows) const {
    const auto c = conditioning_sizes(batch, rows);
    const auto m = modulation_sizes(batch, 1);
    return c.kept + std::max(c.scratch, m.kept + std::max(m.scratch, velocity_bytes(batch, rows)));
  }

  // cond (batch, Lc, context) and y (batch, vec_in_dim) backend float32; ids host (batch, L·, n_axes).
  Conditioning prepare(Context& ctx, Arena<B>& arena, const Tensor<float, B>& cond, const Tensor<float, Cpu>& cond_ids,
                       const Tensor<float, Cpu>& target_ids, const Tensor<float, B>& y) const {
    EPONA_CHECK(cond.dim() == 3 && cond.size(2) == cfg_.context_in_dim, "DiT condition must be (B, L, ",
                cfg_.context_in_dim, "), got ", shape_str(cond.shape()));
    const std::int64_t batch = cond.size(0);
    EPONA_CHECK(target_ids.dim() == 3, "DiT target ids must be (B, L, axes), got ", shape_str(target_ids.shape()));
    const nn::JointRows rows{cond.size(1), target_ids.size(1)};
    const auto axes = static_cast<std::int64_t>(cfg_.axes_dim.size());
    check_shape(cond_ids, {batch, rows.cond, axes}, "DiT condition ids");
    check_shape(target_ids, {batch, rows.target, axes}, "DiT target ids");
    if (vector_in_) check_shape(y, {batch, cfg_.vec_in_dim}, "DiT vector input y");
    Conditioning c = plan_conditioning(arena, batch, rows);
    trunk_.queue().side(ctx);  // the blocks' second queue exists before any sampling loop is recorded
    {
      ArenaScope<B> scope(arena);
      auto s = plan_conditioning_scratch(arena, batch, rows);
      cond_in_(ctx, as_activation(ctx, cond, s.cond), c.cond);
      if (vector_in_) (*vector_in_)(ctx, as_activation(ctx, y, s.y), s.vec_hidden, c.vec_y);
    }
    c.shared_rope = same_items(cond_ids) && same_items(target_ids);
    const auto& host = rope_table(joint_ids(cond_ids, target_ids, c.shared_rope ? 1 : batch));
    auto cos = c.rope.cos.slice(0, host.rows()), sin = c.rope.sin.slice(0, host.rows());
    BackendTraits<B>::upload_into(ctx, host.cos, cos);
    BackendTraits<B>::upload_into(ctx, host.sin, sin);
    return c;
  }

  // The modulation table for timesteps t (batch, times) (host): vec = time_in(temb(t)) (+
  // vector_in(y)), then every block's Linear(SiLU(vec)) — each a GEMM over all batch·times rows.
  Modulations modulations(Context& ctx, Arena<B>& arena, const Conditioning& c, const Tensor<float, Cpu>& t) const {
    EPONA_CHECK(t.dim() == 2 && t.size(0) == c.batch && t.size(1) >= 1, "DiT timesteps must be (", c.batch,
                ", times), got ", shape_str(t.shape()));
    return modulations_of(ctx, arena, c, t);
  }

  // v = DiT(x, t_i) for every batch item, with the modulations of timestep `time` of m.
  // x (batch, Lx, in) float32; out (batch, Lx, out).
  void velocity(Context& ctx, Arena<B>& arena, const Conditioning& c, const Modulations& m, std::int64_t time,
                const Tensor<float, B>& x, Tensor<A, B>& out) const {
    evaluate(ctx, arena, c, m, time, x, out);
  }

  // The official forward(x, ids, cond, cond_ids, t, y) in one call; t (batch) on the host.
  void forward(Context& ctx, Arena<B>& arena, const Tensor<float, B>& x, const Tensor<float, Cpu>& x_ids,
               const Tensor<float, B>& cond, const Tensor<float, Cpu>& cond_ids, const Tensor<float, Cpu>& t,
               const Tensor<float, B>& y, Tensor<A, B>& out) const {
    ArenaScope<B> scope(arena);
    const Conditioning c = prepare(ctx, arena, cond, cond_ids, x_ids, y);
    check_shape(t, {c.batch}, "DiT timesteps t");
    const Modulations m = modulations(ctx, arena, c, t.reshape({c.batch, 1}));
    velocity(ctx, arena, c, m, 0, x, out);
  }

  // Samples from the noise in x (batch, Lx, in) to the sample, in place, over `grid` with
  // `solver` (the official: Euler). The loop enqueues no host work: on the GPU it is recorded
  // once and replayed as a graph; the solver's scratch states are taken before the recording.
  void sample(Context& ctx, Arena<B>& arena, const Conditioning& c, const std::vector<float>& grid,
              Tensor<float, B>& x, flow::SolverKind solver = flow::SolverKind::euler) const {
    EPONA_CHECK(cfg_.in_channels == cfg_.out_channels, "DiT sampling needs in_channels == out_channels");
    flow::with_solver<B>(solver, grid, [&](const auto& s) { sample_with(ctx, arena, c, s, solver, x); });
  }

  const SamplerOptions& sampler_options() const { return options_; }
  // Takes effect at the next sample (the recorded loop is dropped); a run-time switch, as the
  // recorded loop itself, so a const model takes it.
  void set_sampler_options(const SamplerOptions& o) const {
    options_ = o;
    reset_sampler_graph();
  }

  // The recorded sampling loop (on the GPU: how often it was captured, how long that took).
  const typename BackendTraits<B>::GraphCache& sampler_graph() const { return graph_; }
  // Drops the recorded loop so the next sample records it again (e.g. after a kernel choice
  // such as the GEMM tuning changed).
  void reset_sampler_graph() const {
    if constexpr (requires { graph_.reset(); }) graph_.reset();
  }

  // FLOPs of one velocity evaluation including cond_in, batch 1: `executed` counts what runs
  // (the last single block updates only the target rows); otherwise what the official code
  // computes (every row of every block).
  nn::Flops forward_flops(const nn::JointRows& rows, bool executed = true) const {
    nn::Flops f{input_.flops(rows.target) + time_in_.flops(1) + cond_in_.flops(rows.cond), 0};
    if (vector_in_) f.gemm += vector_in_->flops(1);
    return f + trunk_.flops(rows, executed);
  }

 private:
  using Scratch = nn::DitScratch<B, A>;
  // sample() for one solver: the modulations of every evaluation time (k of the velocity
  // contract indexes them), the velocity, the cast state and the solver's scratch, then the loop.
  template <class Solver>
  void sample_with(Context& ctx, Arena<B>& arena, const Conditioning& c, const Solver& solver, flow::SolverKind kind,
                   Tensor<float, B>& x) const {
    const auto& times = solver.evaluation_times();
    const auto evaluations = static_cast<std::int64_t>(times.size());
    ArenaScope<B> scope(arena);
    Tensor<float, Cpu> t({modulation_rows(c.batch), evaluations});
    for (std::int64_t b = 0; b < t.size(0); ++b) std::copy_n(times.data(), evaluations, t[b].data());
    const Modulations m = modulations_of(ctx, arena, c, t);
    auto v = arena.template take<A>({c.batch, c.rows.target, cfg_.out_channels});
    Tensor<A, B> x_cast;  // the state rounded to the GEMM type, updated by each step
    if constexpr (kConvertInputs) x_cast = arena.template take<A>(x.shape());
    ConditionFront front = plan_front(arena, c.batch, c.rows);
    flow::SolverScratch<B> scratch;
    for (int j = 0; j < Solver::scratch_states; ++j) scratch.states[j] = arena.template take<float>(x.shape());
    GraphKey key{address(this), address(x.data()), address(v.data()), address(c.cond.data()), address(m.table.data()),
                 arena.mark(), static_cast<std::uint64_t>(c.batch), static_cast<std::uint64_t>(c.rows.cond),
                 static_cast<std::uint64_t>(c.rows.target), static_cast<std::uint64_t>(kind)};
    for (float g : solver.grid) key.push_back(std::bit_cast<std::uint32_t>(g));
    graph_.run(ctx, key, [&] {
      front.issued = -1;
      const auto velocity = [&](std::int64_t k, float, const auto& state, Tensor<A, B>& vel) {
        evaluate(ctx, arena, c, m, k, state, vel, front.qkv.empty() ? nullptr : &front);
      };
      if constexpr (kConvertInputs)
        solver.sample_cast(ctx, x, x_cast, v, velocity, scratch);
      else
        solver.sample(ctx, x, v, velocity, scratch);
    });
  }

  // Bytes a stage keeps (its result) and the scratch it releases on return.
  struct Sizes {
    std::size_t kept = 0, scratch = 0;
    std::size_t total() const { return kept + scratch; }
  };
  struct ConditioningScratch {
    Tensor<A, B> cond, y;      // the float32 inputs as GEMM operands (empty when A is float)
    Tensor<A, B> vec_hidden;   // (batch, D) vector_in's hidden layer
  };
  struct ModulationScratch {
    Tensor<A, B> temb;              // (n, time_dim)
    Tensor<A, B> hidden, vec, silu; // (n, D)
  };
  // The sampler's pipelined condition front (SamplerOptions::pipelined_condition): the first
  // double block's qkv table and the front's own norm output. One table serves every step:
  // step i + 1's front is enqueued on the side queue at the end of step i, and the first
  // double block's fork after its joint attention (the table's only reader) has put the side
  // queue behind that read already.
  struct ConditionFront {
    Tensor<A, B> qkv;       // (batch, rows + pad, 3D)
    Tensor<A, B> modulated; // (items of a pass·(rows + pad), D): the condition rows' norm, as a pass lays them out
    std::int64_t issued = -1;  // the last step whose front is enqueued
    A* table(std::int64_t b) const { return qkv.data() + b * qkv.size(1) * qkv.size(2); }
  };

  static std::uint64_t address(const void* p) { return static_cast<std::uint64_t>(reinterpret_cast<std::uintptr_t>(p)); }

  // The last single block only needs to update the target rows (the final layer reads no others).

  // A float32 input as a GEMM operand: itself when A is float, else converted into `buffer`.
  const Tensor<A, B>& as_activation(Context& ctx, const Tensor<float, B>& x, Tensor<A, B>& buffer) const {
    if constexpr (kConvertInputs) {
      convert(ctx, x.data(), buffer.data(), x.numel());
      buffer = buffer.reshape(x.shape());
      return buffer;
    } else {
      (void)ctx, (void)buffer;
      return x;
    }
  }

  template <class Alloc>
  Conditioning plan_conditioning(Alloc& a, std::int64_t batch, const nn::JointRows& rows) const {
    const std::int64_t pairs = trunk_.widths().head_dim() / 2;
    Conditioning c;
    c.batch = batch;
    c.rows = rows;
    c.cond = a.template take<A>({batch, rows.cond, cfg_.hidden_size});
    if (vector_in_) c.vec_y = a.template take<A>({batch, cfg_.hidden_size});
    c.rope.cos = a.template take<float>({batch * rows.total(), pairs});
    c.rope.sin = a.template take<float>({batch * rows.total(), pairs});
    return c;
  }
  template <class Alloc>
  ConditioningScratch plan_conditioning_scratch(Alloc& a, std::int64_t batch, const nn::JointRows& rows) const {
    ConditioningScratch s;
    if (kConvertInputs) s.cond = a.template take<A>({batch, rows.cond, cfg_.context_in_dim});
    if (vector_in_) {
      if (kConvertInputs) s.y = a.template take<A>({batch, cfg_.vec_in_dim});
      s.vec_hidden = a.template take<A>({batch, cfg_.hidden_size});
    }
    return s;
  }
  Sizes conditioning_sizes(std::int64_t batch, const nn::JointRows& rows) const {
    ArenaCounter<B> kept, scratch;
    plan_conditioning(kept, batch, rows);
    plan_conditioning_scratch(scratch, batch, rows);
    return {kept.bytes(), scratch.bytes()};
  }

  // A sample's items share their modulations when the DiT has no vector_in: vec_i is then the
  // time's alone (the TrajDiT), so the table is one row per evaluation whatever the batch (the
  // batch-1 table, bit for bit; 100 rows instead of K·100 for K plan hypotheses).
  bool shares_modulations() const { return !vector_in_; }
  // The modulation table's rows for a sample of `batch` items: 1 where they share it.
  std::int64_t modulation_rows(std::int64_t batch) const { return shares_modulations() ? 1 : batch; }

  // The modulation table for timesteps t (rows, times) (host): per item (rows = c.batch), or
  // shared by every item (rows = 1; only where shares_modulations()). vec = time_in(temb(t))
  // (+ vector_in(y)), then every block's Linear(SiLU(vec)), each a GEMM over all rows·times.
  Modulations modulations_of(Context& ctx, Arena<B>& arena, const Conditioning& c, const Tensor<float, Cpu>& t) const {
    const bool shared = t.size(0) == 1 && c.batch > 1;
    EPONA_CHECK(!shared || shares_modulations(), "DiT: items cannot share modulations with vector_in");
    const std::int64_t rows = t.size(0), times = t.size(1), n = t.numel(), D = cfg_.hidden_size;
    Modulations m = plan_modulations(arena, rows, times);
    m.shared = shared;
    ArenaScope<B> scope(arena);
    auto s = plan_modulation_scratch(arena, rows, times);
    Tensor<float, Cpu> temb({n, cfg_.time_dim});
    nn::timestep_embedding(t.data(), n, cfg_.time_dim, cfg_.time_max_period, cfg_.time_factor, temb.data());
    upload_as(ctx, temb, s.temb);
    time_in_(ctx, s.temb, s.hidden, s.vec);
    if (vector_in_)
      for (std::int64_t b = 0; b < rows; ++b)
        add_row_broadcast(ctx, s.vec.data() + b * times * D, c.vec_y[b].data(), times, D);
    silu_to(ctx, s.vec.data(), s.silu.data(), n * D);
    trunk_.modulations(ctx, s.silu.data(), n, m.table.data(), m.width);
    return m;
  }

  template <class Alloc>
  Modulations plan_modulations(Alloc& a, std::int64_t batch, std::int64_t times) const {
    Modulations m;
    m.times = times;
    m.width = trunk_.modulation_width();
    m.table = a.template take<A>({batch * times, m.width});
    return m;
  }
  template <class Alloc>
  ModulationScratch plan_modulation_scratch(Alloc& a, std::int64_t batch, std::int64_t times) const {
    const std::int64_t n = batch * times, D = cfg_.hidden_size;
    return {a.template take<A>({n, cfg_.time_dim}), a.template take<A>({n, D}), a.template take<A>({n, D}),
            a.template take<A>({n, D})};
  }
  Sizes modulation_sizes(std::int64_t batch, std::int64_t times) const {
    ArenaCounter<B> kept, scratch;
    plan_modulations(kept, batch, times);
    plan_modulation_scratch(scratch, batch, times);
    return {kept.bytes(), scratch.bytes()};
  }

  // Whether the sampler runs the condition front ahead (SamplerOptions::pipelined_condition).
  bool pipelines_condition(const nn::JointRows& rows) const {
    return options_.pipelined_condition && trunk_.has_double_blocks() && !nn::streams_pairable(rows);
  }
  template <class Alloc>
  ConditionFront plan_front(Alloc& a, std::int64_t batch, const nn::JointRows& rows) const {
    ConditionFront f;
    if (!pipelines_condition(rows)) return f;
    const std::int64_t D = cfg_.hidden_size, table_rows = rows.total() + nn::paired_padding(rows);
    f.qkv = a.template take<A>({batch, table_rows, 3 * trunk_.widths().attention_width()});
    f.modulated = a.template take<A>({folded_items(batch) * table_rows, D});
    return f;
  }
  // Enqueues step `time`'s condition front for every batch item on the side queue (after a
  // fork when the side queue has not yet seen this step's inputs).
  void issue_front(Context& ctx, const Conditioning& c, const Modulations& m, std::int64_t time, ConditionFront& f,
                   bool fork) const {
    if (fork) trunk_.queue().fork(ctx);
    Context& side = trunk_.queue().side(ctx);
    each_pass(c.batch, [&](std::int64_t first, std::int64_t n) {
      trunk_.condition_front(side, c.cond[first].data(), f.modulated, f.table(first), c.rows, pass_rope(c, first, n),
                             m.row(first, time), pass_items(c, m, n));
    });
    f.issued = time;
  }

  // The passes a batch runs in through the blocks (kMaxFoldedItems items at most each): f(first, n)
  // for items [first, first + n).
  template <class F>
  static void each_pass(std::int64_t batch, F&& f) {
    const std::int64_t per_pass = folded_items(batch);
    for (std::int64_t first = 0; first < batch; first += per_pass) f(first, std::min(per_pass, batch - first));
  }
  // How a pass of n items lies in the blocks' scratch, and the pass's RoPE tables.
  nn::DitItems pass_items(const Conditioning& c, const Modulations& m, std::int64_t n) const {
    return {n, c.rows.total() + nn::paired_padding(c.rows), m.shared ? 0 : m.times * m.width,
            c.shared_rope ? 0 : c.rows.total()};
  }
  nn::RopeTable<B> pass_rope(const Conditioning& c, std::int64_t first, std::int64_t n) const {
    const std::int64_t rows = c.rows.total(), from = c.shared_rope ? 0 : first * rows;
    const std::int64_t to = c.shared_rope ? rows : (first + n) * rows;
    return {c.rope.cos.slice(from, to), c.rope.sin.slice(from, to)};
  }
  // Whether every item of a (batch, ...) tensor equals item 0.
  static bool same_items(const Tensor<float, Cpu>& t) {
    const std::int64_t per_item = t.numel() / t.size(0);
    for (std::int64_t b = 1; b < t.size(0); ++b)
      if (std::memcmp(t[b].data(), t.data(), sizeof(float) * per_item) != 0) return false;
    return true;
  }

  // The block scratch of `batch` items (each padded for the double blocks' paired products),
  // and the input x as a GEMM operand (empty when A is float).
  template <class Alloc>
  std::pair<Scratch, Tensor<A, B>> plan_velocity(Alloc& a, std::int64_t batch, const nn::JointRows& rows) const {
    auto s = trunk_.plan_scratch(a, rows, batch);
    Tensor<A, B> x_in;
    if (kConvertInputs) x_in = a.template take<A>({batch, rows.target, cfg_.in_channels});
    return {s, x_in};
  }

  // The RoPE table of joint ids, rebuilt only when the ids change (they are fixed by the
  // configuration in the world model; the float64 table costs ~1 ms of host time per build).
  const nn::RopeTable<Cpu>& rope_table(const Tensor<float, Cpu>& ids) const {
    auto& cache = rope_cache_;
    const bool same = cache.ids.shape() == ids.shape() &&
                      (ids.numel() == 0 || std::memcmp(cache.ids.data(), ids.data(), ids.nbytes()) == 0);
    if (!same || cache.table.cos.empty()) {
      cache.table = nn::nd_rope_table(ids, cfg_.axes_dim, cfg_.theta);
      cache.ids = ids;
    }
    return cache.table;
  }

  // The joint ids of the first `batch` items, item after item.
  static Tensor<float, Cpu> joint_ids(const Tensor<float, Cpu>& cond_ids, const Tensor<float, Cpu>& target_ids,
                                      std::int64_t batch) {
    const std::int64_t lc = cond_ids.size(1), lx = target_ids.size(1), k = cond_ids.size(2);
    Tensor<float, Cpu> ids({batch * (lc + lx), k});
    for (std::int64_t b = 0; b < batch; ++b) {
      std::memcpy(ids[b * (lc + lx)].data(), cond_ids[b].data(), sizeof(float) * lc * k);
      std::memcpy(ids[b * (lc + lx) + lc].data(), target_ids[b].data(), sizeof(float) * lx * k);
    }
    return ids;
  }

  // The target rows of z = input(x) of every batch item (the trunk reads the condition rows
  // from cond_in's output). x (batch, Lx, in) is float32 (converted into x_in when the GEMMs
  // take another type) or already of the GEMM type.
  template <class X>
  void embed_target(Context& ctx, Scratch& s, const nn::JointRows& rows, const Tensor<X, B>& x, Tensor<A, B>& x_in) const {
    const A* in = nullptr;
    if constexpr (std::is_same_v<X, A>) {
      (void)x_in;
      in = x.data();
    } else {
      in = as_activation(ctx, x, x_in).data();
    }
    const std::int64_t C = cfg_.in_channels, D = cfg_.hidden_size;
    input_.items(ctx, in, C, rows.target * C, rows.target, s.z.data() + rows.cond * D, D, s.items.rows * D,
                 s.items.count);
  }

  // velocity() for an input x of type X: float32 (converted per batch item when the GEMMs take
  // another type) or already the GEMM type A (the sampler keeps its state rounded for them).
  // From the sampler, `front`: the pipelined condition front (this step's issued ahead if it
  // is not yet, the next step's issued at the end).
  template <class X>
  void evaluate(Context& ctx, Arena<B>& arena, const Conditioning& c, const Modulations& m, std::int64_t time,
                const Tensor<X, B>& x, Tensor<A, B>& out, ConditionFront* front = nullptr) const {
    check_shape(x, {c.batch, c.rows.target, cfg_.in_channels}, "DiT input x");
    check_shape(out, {c.batch, c.rows.target, cfg_.out_channels}, "DiT velocity output");
    EPONA_CHECK(time >= 0 && time < m.times, "DiT: timestep index ", time, " outside the ", m.times, " prepared");
    if (front && front->issued != time) issue_front(ctx, c, m, time, *front, true);
    // The items in one pass through the blocks (up to kMaxFoldedItems a pass): the batch folded
    // into the products' rows.
    ArenaScope<B> scope(arena);
    auto [scratch, x_in] = plan_velocity(arena, folded_items(c.batch), c.rows);
    each_pass(c.batch, [&](std::int64_t first, std::int64_t n) {
      Scratch s = scratch;
      s.items = pass_items(c, m, n);
      auto x_pass = x.slice(first, first + n);
      auto x_in_pass = x_in.empty() ? x_in : x_in.slice(0, n);
      embed_target(ctx, s, c.rows, x_pass, x_in_pass);
      // The first block reads the condition rows from cond_in's output (step-invariant) and
      // writes their update into s.z: no per-step copy.
      nn::TrunkInputs<B, A> in{c.cond[first].data(), {}};
      if (front) {
        const auto table = front->qkv.slice(first, first + n);
        in.cond_qkv = Tensor<A, B>::view(table.data(), {n * s.items.rows, 3 * trunk_.widths().attention_width()}, table.storage());
      }
      auto o = out.slice(first, first + n);
      trunk_(ctx, s, c.rows, pass_rope(c, first, n), m.row(first, time), o, in);
    });
    if (front && time + 1 < m.times) issue_front(ctx, c, m, time + 1, *front, false);
  }

  FluxDitConfig cfg_;
  nn::Linear<B, W> input_;  // img_in / traj_in
  nn::MlpEmbedder<B, W> time_in_;
  std::optional<nn::MlpEmbedder<B, W>> vector_in_;
  nn::Linear<B, W> cond_in_;
  nn::DitTrunk<B, W> trunk_;  // double_blocks., single_blocks., final_layer.
  mutable typename BackendTraits<B>::GraphCache graph_;  // the recorded sampling loop
  struct RopeCache {
    Tensor<float, Cpu> ids;
    nn::RopeTable<Cpu> table;
  };
  mutable RopeCache rope_cache_;
  mutable SamplerOptions options_ = SamplerOptions::from_environment();
};

}  // namespace epona::model
