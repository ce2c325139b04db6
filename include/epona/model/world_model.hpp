// epona/model/world_model.hpp — the Epona world model (models/model.py
// `TrainTransformersDiT`): MST + TrajDiT + VisDiT bound from one checkpoint (prefixes
// `module.model.`, `module.traj_dit.`, `module.dit.`), and the inference entry points:
// plan (traj_only), predict_next with a given action (`generate_gt_pose_gt_yaw`) or a
// self-predicted one (`step_eval(self_pred_traj=True)`). Noise from a seed (torch-compatible
// draws, trajectory noise then latent noise per step) or supplied by the caller.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "epona/core/arena.hpp"
#include "epona/core/error.hpp"
#include "epona/core/rng.hpp"
#include "epona/core/tensor.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config/world_config.hpp"
#include "epona/model/flux_dit.hpp"
#include "epona/model/mst.hpp"
#include "epona/model/pose_tokenizer.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/parameter.hpp"

namespace epona {

// The conditioning window of a batch of Bt scenes, oldest frame first.
struct History {
  Tensor<float, Cpu> latents;   // (Bt, F, L, C_vae) DC-AE latents, tokens row-major over (h, w)
  Tensor<float, Cpu> rel_pose;  // (Bt, F, 2) motion (x fwd, y left; metres) into each window frame
  Tensor<float, Cpu> rel_yaw;   // (Bt, F, 1) heading change (degrees) into each window frame
};

// The motion from the last window frame into the frame to generate.
struct NextAction {
  Tensor<float, Cpu> rel_pose;  // (Bt, 1, 2)
  Tensor<float, Cpu> rel_yaw;   // (Bt, 1, 1)
};

// Where the sampler's starting noise comes from: a torch-compatible generator (draw order
// of step_eval: trajectory noise (Bt, traj_len, 3), then latent noise (Bt, L, C) per step), or
// one generator per batch item (item b draws what seeded(seeds[b]) draws for a batch of 1, so
// an item's noise does not depend on the batch it runs in), or tensors supplied per step
// ((S, Bt, traj_len, 3) and (S, Bt, L, C); draw s takes [s]).
class NoiseSource {
 public:
  // The official semantics: the whole batch from one generator (golden parity depends on it).
  static NoiseSource seeded(std::uint64_t seed) {
    NoiseSource n;
    n.generator_.emplace(seed);
    return n;
  }
  static NoiseSource seeded_per_item(const std::vector<std::uint64_t>& seeds) {
    EPONA_CHECK(!seeds.empty(), "per-item noise needs at least one seed");
    NoiseSource n;
    n.item_generators_.reserve(seeds.size());
    for (const std::uint64_t seed : seeds) n.item_generators_.emplace_back(seed);
    return n;
  }
  static NoiseSource supplied(Tensor<float, Cpu> trajectory, Tensor<float, Cpu> latent) {
    NoiseSource n;
    n.traj_ = std::move(trajectory);
    n.latent_ = std::move(latent);
    return n;
  }
  Tensor<float, Cpu> trajectory(const Shape& shape) { return draw(traj_, traj_drawn_, shape, "trajectory"); }
  Tensor<float, Cpu> latent(const Shape& shape) { return draw(latent_, latent_drawn_, shape, "latent"); }

  // Throws unless `count` more draws of each shape are available (checked before any work).
  void require(std::int64_t traj_count, const Shape& traj_shape, std::int64_t latent_count,
               const Shape& latent_shape) const {
    if (generator_) return;
    if (!item_generators_.empty()) {
      if (traj_count > 0) require_item_batch(traj_shape, "trajectory");
      if (latent_count > 0) require_item_batch(latent_shape, "latent");
      return;
    }
    require_one(traj_, traj_drawn_, traj_count, traj_shape, "trajectory");
    require_one(latent_, latent_drawn_, latent_count, latent_shape, "latent");
  }

 private:
  Tensor<float, Cpu> draw(const Tensor<float, Cpu>& supplied, std::int64_t& drawn, const Shape& shape,
                          const char* what) {
    if (generator_) return generator_->randn(shape);
    if (!item_generators_.empty()) return draw_per_item(shape, what);
    require_one(supplied, drawn, 1, shape, what);
    return supplied[drawn++].clone();
  }
  // Item b's rows from item b's generator, drawn as a batch of 1.
  Tensor<float, Cpu> draw_per_item(const Shape& shape, const char* what) {
    require_item_batch(shape, what);
    Shape item_shape = shape;
    item_shape[0] = 1;
    Tensor<float, Cpu> out(shape);
    const std::int64_t row = out.numel() / shape[0];
    for (std::size_t b = 0; b < item_generators_.size(); ++b) {
      const auto item = item_generators_[b].randn(item_shape);
      std::copy_n(item.data(), row, out.data() + static_cast<std::int64_t>(b) * row);
    }
    return out;
  }
  void require_item_batch(const Shape& shape, const char* what) const {
    const auto seeds = static_cast<std::int64_t>(item_generators_.size());
    EPONA_CHECK(!shape.empty() && shape[0] == seeds, what, " noise of shape ", shape_str(shape), " is for a batch of ",
                shape.empty() ? 0 : shape[0], " but ", seeds, " per-item seed(s) were given (one per batch item)");
  }
  static void require_one(const Tensor<float, Cpu>& supplied, std::int64_t drawn, std::int64_t count,
                          const Shape& shape, const char* what) {
    if (count <= 0) return;
    EPONA_CHECK(!supplied.empty(), "no ", what, " noise supplied (", count, " draw(s) of ", shape_str(shape),
                " needed)");
    Shape per_step(supplied.shape().begin() + 1, supplied.shape().end());
    EPONA_CHECK(supplied.dim() >= 1 && per_step == shape, what, " noise has shape ", shape_str(supplied.shape()),
                "; each step needs ", shape_str(shape), " (steps first)");
    EPONA_CHECK(drawn + count <= supplied.size(0), what, " noise for ", supplied.size(0), " step(s) supplied, ",
                drawn + count, " needed");
    for (std::int64_t i = 0; i < supplied.numel(); ++i)
      EPONA_CHECK(std::isfinite(supplied.data()[i]), what, " noise has a non-finite value at flat index ", i);
  }

  std::optional<TorchGenerator> generator_;
  std::vector<TorchGenerator> item_generators_;  // one per batch item, in batch order
  Tensor<float, Cpu> traj_, latent_;
  std::int64_t traj_drawn_ = 0, latent_drawn_ = 0;
};

// Which flow solver each DiT samples with, and how many steps (the planner's TrajDiT and the
// video's VisDiT need not share them).
struct DitSamplers {
  flow::SolverSetting plan, video;
  // The official sampler: `steps` Euler steps for both.
  static DitSamplers euler(std::int64_t steps) { return {{flow::SolverKind::euler, steps}, {flow::SolverKind::euler, steps}}; }
};

struct SampleOptions {
  std::optional<std::int64_t> steps;  // steps of each DiT; default the config's num_sampling_steps
  std::optional<std::int64_t> plan_steps, video_steps;  // one DiT's steps, overriding `steps`
  flow::SolverKind solver = flow::SolverKind::euler;    // each DiT's solver (the official: Euler)
  std::optional<flow::SolverKind> plan_solver, video_solver;  // one DiT's, overriding `solver`
  std::uint64_t seed = 0;             // noise from TorchGenerator(seed) ...
  std::vector<std::uint64_t> item_seeds;  // ... or item b's from TorchGenerator(item_seeds[b]) (one per item) ...
  std::optional<NoiseSource> noise;   // ... unless a source is given
};

// Each DiT's solver and steps: its own if given, else the shared ones (steps: else `default_steps`,
// the config's num_sampling_steps). Throws on a step count outside [1, max_sampling_steps].
inline void check_samplers(const DitSamplers& s) {
  check_sampling_steps(s.plan.steps, "planner (TrajDiT) sampling steps");
  check_sampling_steps(s.video.steps, "video (VisDiT) sampling steps");
}
inline DitSamplers samplers_for(const SampleOptions& opt, std::int64_t default_steps) {
  const std::int64_t steps = opt.steps.value_or(default_steps);
  check_sampling_steps(steps);
  DitSamplers s{{opt.plan_solver.value_or(opt.solver), opt.plan_steps.value_or(steps)},
                {opt.video_solver.value_or(opt.solver), opt.video_steps.value_or(steps)}};
  check_samplers(s);
  return s;
}

struct StepResult {
  Tensor<float, Cpu> trajectory;  // (Bt, traj_len, 3) metres/degrees; empty when the action was given
  Tensor<float, Cpu> latent;      // (Bt, L, C_vae); empty for plan()
};

// Intermediate values of one step, for observers (parity tests, diagnostics).
template <class B>
struct StepDetails {
  Tensor<float, B> stt_features;    // (Bt, T, C) MST output of the last window frame
  Tensor<float, B> pose_emb;        // (Bt, 3C) the action embedding given to the VisDiT
  Tensor<float, Cpu> pred_pose_idx; // (Bt, 1, 2) tokenized first predicted waypoint (self-predicted)
  Tensor<float, Cpu> pred_yaw_idx;  // (Bt, 1, 1)
};

namespace model {

template <class B = Cpu, class W = float>
class WorldModel {
 public:
  using Context = BackendContext<B>;
  using StepObserver = std::function<void(const StepDetails<B>&)>;
  using VisShardSum = ShardSum<Context, Activation<B, W>>;

  // A world model whose VisDiT is one shard of a tensor-parallel group (docs/parallel.md): its
  // heads and MLP columns split `vis.size` ways, its partial outputs summed through `sum`
  // (which must outlive the model). The MST and the TrajDiT stay whole on every shard. Each
  // shard runs the same calls with the same inputs and seeds (a thread of its own, its GPU the
  // thread's current device) and gets the same results.
  struct VisShard {
    TensorShard vis;
    const VisShardSum* sum = nullptr;
  };

  // Binds the three networks from one weight map (all keys under "module." must be used;
  // other keys, e.g. a merged DC-AE, are ignored). Every problem is reported at once. With
  // `shard`, the VisDiT binds its shard's cut of the map.
  static WorldModel load(const io::TensorMap& weights, const WorldModelConfig& config = {}, const VisShard& shard = {}) {
    config.validate();
    config.check_size(parameter_list(config).count());
    EPONA_CHECK(!shard.vis.sharded() || shard.sum, "WorldModel: a VisDiT shard (", shard.vis.rank, " of ",
                shard.vis.size, ") needs its group's sum");
    WorldModel m(config, shard.vis);
    const io::TensorMap cut = shard.vis.sharded() ? m.vis_.shard_weights(weights, "module.dit.") : io::TensorMap();
    const io::TensorMap& map = shard.vis.sharded() ? cut : weights;
    io::BindReport report(map);
    bool any_traj = false;  // named first: the list of its missing keys may get truncated
    for (const auto& name : map.names()) any_traj = any_traj || name.rfind("module.traj_dit.", 0) == 0;
    if (!any_traj)
      report.problem("no TrajDiT weights (no key starts with 'module.traj_dit.'; the official loader would "
                     "silently keep random ones)");
    nn::ParamBinder binder(report);
    m.visit_params(binder);
    report.finish(true, [](const std::string& k) { return k.rfind("module.", 0) != 0; });
    if (shard.vis.sharded()) m.vis_.set_shard_sum(shard.sum);
    return m;
  }

  // From a weight file: the official torch.save checkpoint (its "model_state_dict") or a
  // safetensors file with the same keys. The file is released once the weights are bound.
  static WorldModel load_file(const std::string& path, const WorldModelConfig& config = {}) {
    return load(io::load_weights(path), config);
  }

  // The parameter tree of the three networks under their official prefixes (nn/parameter.hpp).
  template <class V>
  void visit_params(V& v) {
    visit_parts(mst_, vis_, traj_, v);
  }

  // The parameter tree of a configuration without weights (names, shapes; counts by prefix):
  // the three networks' skeleton visited with nn::ParamList. Values that shape no parameter need
  // not fit: the DiTs' RoPE split (a configuration read from a checkpoint's shapes may assume
  // one from another model) and the frame size and window, which size the MST's RoPE table (the
  // one thing its constructor allocates: the skeleton's is 1x1, one frame). The rest is
  // validated; the sizes are not (WorldModelConfig::check_size).
  static nn::ParamList parameter_list(const WorldModelConfig& config) {
    WorldModelConfig shapes = config;
    fit_rope_axes(shapes.axes_dim_dit, shapes.n_embd_dit, shapes.n_head_dit);
    fit_rope_axes(shapes.axes_dim_dit_traj, shapes.n_embd_dit_traj, shapes.n_head_dit_traj);
    shapes.validate();
    MstConfig mst_shapes = MstConfig::from(shapes);
    mst_shapes.condition_frames = mst_shapes.latent_h = mst_shapes.latent_w = 1;
    SpatialTemporalTransformer<B, W> mst(mst_shapes);
    FluxDiT<B, W> vis(FluxDitConfig::vis(shapes)), traj(FluxDitConfig::traj(shapes));
    nn::ParamList list;
    visit_parts(mst, vis, traj, list);
    return list;
  }

  const WorldModelConfig& config() const { return cfg_; }
  Context& context() { return *ctx_; }
  const SpatialTemporalTransformer<B, W>& mst() const { return mst_; }
  const FluxDiT<B, W>& vis_dit() const { return vis_; }
  const FluxDiT<B, W>& traj_dit() const { return traj_; }
  // The step workspace's size: set by the first step, grown only for a larger batch or more
  // sampling steps (WorldSession checks that its steps leave it alone).
  std::size_t arena_capacity() const { return arena_.capacity(); }

  // traj_only: the planned trajectory (Bt, traj_len, 3) in metres/degrees.
  Tensor<float, Cpu> plan(const History& h, const SampleOptions& opt = {}) {
    NoiseSource noise = noise_for(opt);
    return run_step(h, nullptr, /*want_latent=*/false, samplers_of(opt), noise, {}).trajectory;
  }

  // K trajectories of one scene (a window of Bt = 1), (K, traj_len, 3): the MST runs once and
  // its features condition one TrajDiT run over a batch of K noises. Hypothesis k draws the noise
  // plan() draws with seed hypothesis_seed(opt.seed, k), so hypothesis 0 is plan()'s trajectory
  // and each one is what a plan of its seed alone gives.
  Tensor<float, Cpu> plan_hypotheses(const History& h, std::int64_t K, const SampleOptions& opt = {}) {
    EPONA_CHECK(K >= 1 && K <= constants::max_hypotheses, "the number of plan hypotheses must be in [1, ",
                constants::max_hypotheses, "], got ", K);
    EPONA_CHECK(!opt.noise, "plan_hypotheses draws each hypothesis' noise from the seed; it takes no supplied noise");
    EPONA_CHECK(opt.item_seeds.empty(), "plan_hypotheses draws each hypothesis' noise from the one seed; it takes no "
                "per-item seeds");
    const DitSamplers samplers = samplers_of(opt);
    const std::int64_t Bt = validate(h, nullptr, samplers);
    EPONA_CHECK(Bt == 1, "plan_hypotheses plans one scene; the window holds ", Bt);
    arena_.reset();
    arena_.reserve(hypotheses_bytes(K, samplers));
    const StepDetails<B> scene = condition(h, nullptr, Bt);
    StepDetails<B> fan;
    fan.stt_features = repeat_batch(scene.stt_features, K);
    fan.pose_emb = repeat_batch(scene.pose_emb, K);
    const auto ids = prepare_ids(K, cfg_.latent_h(), cfg_.latent_w(), cfg_.tokens_per_frame(), cfg_.traj_len);
    auto traj = sample(traj_, fan, ids.cond, ids.traj, hypothesis_noise(K, opt.seed), cfg_.traj_len, samplers.plan);
    TrajectoryScale::from(cfg_).denormalize(traj);
    return traj;
  }
  // The seed of hypothesis k: seed + k·0x9E3779B9. The generator keeps the low 32 bits (as
  // torch.manual_seed does); golden-ratio steps keep the K seeds far apart in that space, so eval's
  // seed + i for clip i meets no other clip's hypotheses below about a million clips.
  static std::uint64_t hypothesis_seed(std::uint64_t seed, std::int64_t k) {
    return seed + static_cast<std::uint64_t>(k) * kHypothesisSeedStep;
  }
  static constexpr std::uint64_t kHypothesisSeedStep = 0x9E3779B9u;

  // The next frame's latent. With `action`: the VisDiT is conditioned on it and no trajectory is
  // sampled; without: the TrajDiT plans first and its first waypoint is the action.
  StepResult predict_next(const History& h, const std::optional<NextAction>& action, const SampleOptions& opt = {}) {
    NoiseSource noise = noise_for(opt);
    return run_step(h, action ? &*action : nullptr, true, samplers_of(opt), noise, {});
  }

  // One generation step drawing from `noise` (the rollout's shared source), `steps` Euler steps.
  StepResult run_step(const History& h, const NextAction* action, bool want_latent, std::int64_t steps,
                      NoiseSource& noise, const StepObserver& observe) {
    return run_step(h, action, want_latent, DitSamplers::euler(steps), noise, observe);
  }
  // The same with each DiT's solver and steps.
  StepResult run_step(const History& h, const NextAction* action, bool want_latent, const DitSamplers& samplers,
                      NoiseSource& noise, const StepObserver& observe) {
    const std::int64_t Bt = validate(h, action, samplers);
    const bool want_traj = action == nullptr;
    noise.require(want_traj ? 1 : 0, traj_noise_shape(Bt), want_latent ? 1 : 0, latent_noise_shape(Bt));
    reserve_arena(Bt, samplers);
    arena_.reset();
    StepResult result;
    StepDetails<B> details = condition(h, action, Bt);
    const auto ids = prepare_ids(Bt, cfg_.latent_h(), cfg_.latent_w(), cfg_.tokens_per_frame(), cfg_.traj_len);
    if (want_traj) {
      result.trajectory = sample(traj_, details, ids.cond, ids.traj, noise.trajectory(traj_noise_shape(Bt)),
                                 cfg_.traj_len, samplers.plan);
      TrajectoryScale::from(cfg_).denormalize(result.trajectory);
    }
    if (want_latent) {
      if (want_traj) embed_first_waypoint(result.trajectory, details);
      result.latent = sample(vis_, details, ids.cond, ids.img, noise.latent(latent_noise_shape(Bt)),
                             cfg_.img_tokens(), samplers.video);
    }
    if (observe) observe(details);
    return result;
  }

  std::int64_t steps_of(const SampleOptions& opt) const {
    const std::int64_t steps = opt.steps.value_or(cfg_.num_sampling_steps);
    check_sampling_steps(steps);
    return steps;
  }
  // Each DiT's solver and steps (samplers_for with the config's num_sampling_steps).
  DitSamplers samplers_of(const SampleOptions& opt) const { return samplers_for(opt, cfg_.num_sampling_steps); }
  static NoiseSource noise_for(const SampleOptions& opt) {
    EPONA_CHECK(!(opt.noise && !opt.item_seeds.empty()), "sample options give both supplied noise and per-item seeds; "
                "give one");
    if (opt.noise) return *opt.noise;
    if (!opt.item_seeds.empty()) return NoiseSource::seeded_per_item(opt.item_seeds);
    return NoiseSource::seeded(opt.seed);
  }
  Shape traj_noise_shape(std::int64_t Bt) const { return {Bt, cfg_.traj_len, constants::traj_token_size}; }
  Shape latent_noise_shape(std::int64_t Bt) const { return {Bt, cfg_.img_tokens(), cfg_.token_dim()}; }

  // Checks a window (and action) against the configuration; returns the batch size. Throws
  // (naming the problem) on any wrong shape or non-finite value, before any work.
  std::int64_t validate(const History& h, const NextAction* action, std::int64_t steps) const {
    return validate(h, action, DitSamplers::euler(steps));
  }
  std::int64_t validate(const History& h, const NextAction* action, const DitSamplers& samplers) const {
    check_samplers(samplers);
    EPONA_CHECK(!h.latents.empty() && h.latents.dim() == 4, "history latents must be (B, F, L, C), got ",
                shape_str(h.latents.shape()));
    const std::int64_t Bt = h.latents.size(0), F = cfg_.condition_frames;
    EPONA_CHECK(Bt >= 1, "history batch is empty");
    EPONA_CHECK(h.latents.size(1) == F, "history has ", h.latents.size(1), " latent frames; the model needs ", F,
                " (condition_frames)");
    check_shape(h.latents, {Bt, F, cfg_.img_tokens(), cfg_.token_dim()}, "history latents");
    check_shape(h.rel_pose, {Bt, F, 2}, "history rel_pose");
    check_shape(h.rel_yaw, {Bt, F, 1}, "history rel_yaw");
    check_finite(h.latents, "history latents");
    check_finite(h.rel_pose, "history rel_pose");
    check_finite(h.rel_yaw, "history rel_yaw");
    if (action) {
      check_shape(action->rel_pose, {Bt, 1, 2}, "next action rel_pose");
      check_shape(action->rel_yaw, {Bt, 1, 1}, "next action rel_yaw");
      check_finite(action->rel_pose, "next action rel_pose");
      check_finite(action->rel_yaw, "next action rel_yaw");
    }
    return Bt;
  }

  // The MST's action-entry indices of a window (pose (Bt, F+1), yaw (Bt, F+1)): the window's F,
  // then the given action or (self-predicted, where entry F only feeds a pose_emb that gets
  // replaced) a repeat of the last entry. Public for callers that run the MST themselves.
  std::pair<Tensor<float, Cpu>, Tensor<float, Cpu>> window_indices(const History& h, const NextAction* action) const {
    const std::int64_t Bt = h.rel_pose.size(0), F = cfg_.condition_frames;
    Tensor<float, Cpu> pose({Bt, F + 1, 2}), yaw({Bt, F + 1, 1});
    for (std::int64_t b = 0; b < Bt; ++b) {
      std::copy_n(h.rel_pose[b].data(), 2 * F, pose[b].data());
      std::copy_n(h.rel_yaw[b].data(), F, yaw[b].data());
      const float* next_pose = action ? action->rel_pose[b].data() : h.rel_pose[b][F - 1].data();
      const float* next_yaw = action ? action->rel_yaw[b].data() : h.rel_yaw[b][F - 1].data();
      std::copy_n(next_pose, 2, pose[b][F].data());
      yaw.at(b, F, 0) = *next_yaw;
    }
    const auto tok = PoseTokenizer::from(cfg_);
    return {tok.poses_to_indices(pose), tok.yaws_to_indices(yaw)};
  }

 private:
  WorldModel(const WorldModelConfig& c, const TensorShard& vis_shard)
      : cfg_(c), mst_(MstConfig::from(c)), vis_(vis_config(c, vis_shard)), traj_(FluxDitConfig::traj(c)) {}
  static FluxDitConfig vis_config(const WorldModelConfig& c, const TensorShard& shard) {
    FluxDitConfig v = FluxDitConfig::vis(c);
    v.shard = shard;
    return v;
  }

  // A RoPE split of the head dim width/heads that validate() accepts, where one exists.
  static void fit_rope_axes(std::array<std::int64_t, 3>& axes, std::int64_t width, std::int64_t heads) {
    if (width <= 0 || heads <= 0 || width % heads != 0) return;
    const std::int64_t head_dim = width / heads;
    if (head_dim >= 6 && head_dim % 2 == 0) axes = {2, 2, head_dim - 4};
  }

  // The official prefixes of the three networks.
  template <class V>
  static void visit_parts(SpatialTemporalTransformer<B, W>& mst, FluxDiT<B, W>& vis, FluxDiT<B, W>& traj, V& v) {
    mst.visit_params("module.model.", v);
    vis.visit_params("module.dit.", v);
    traj.visit_params("module.traj_dit.", v);
  }

  static void check_finite(const Tensor<float, Cpu>& t, const char* what) {
    for (std::int64_t i = 0; i < t.numel(); ++i)
      EPONA_CHECK(std::isfinite(t.data()[i]), what, " has a non-finite value (", t.data()[i], ") at flat index ", i);
  }

  // Arena bytes of one step: the step's persistent tensors plus its largest stage.
  std::size_t step_bytes(std::int64_t Bt, const DitSamplers& s) const {
    ArenaCounter<B> persistent;
    persistent.template take<float>({Bt, cfg_.condition_frames, cfg_.img_tokens(), cfg_.token_dim()});
    persistent.template take<float>({Bt, cfg_.tokens_per_frame(), cfg_.n_embd});
    persistent.template take<float>({Bt, cfg_.pose_emb_dim()});
    persistent.template take<float>(traj_noise_shape(Bt));
    persistent.template take<float>(latent_noise_shape(Bt));
    const nn::JointRows traj_rows{cfg_.tokens_per_frame(), cfg_.traj_len}, img_rows{cfg_.tokens_per_frame(), cfg_.img_tokens()};
    const std::size_t stages[] = {
        mst_.evaluate_workspace_bytes(Bt), mst_.pose_emb_workspace_bytes(Bt),
        traj_.conditioning_bytes(Bt, traj_rows) + traj_.sample_bytes(Bt, traj_rows, s.plan.steps, s.plan.kind),
        vis_.conditioning_bytes(Bt, img_rows) + vis_.sample_bytes(Bt, img_rows, s.video.steps, s.video.kind)};
    std::size_t largest = 0;
    for (auto s : stages) largest = std::max(largest, s);
    return persistent.bytes() + largest;
  }
  // Grows the arena only when the batch or evaluation count grows (never inside a sampling loop).
  void reserve_arena(std::int64_t Bt, const DitSamplers& s) {
    arena_.reset();
    arena_.reserve(step_bytes(Bt, s));
  }

  // Self-predicted action: tokenize waypoint 0 and replace pose_emb by get_pose_emb of it.
  void embed_first_waypoint(const Tensor<float, Cpu>& traj, StepDetails<B>& d) {
    const std::int64_t Bt = traj.size(0);
    Tensor<float, Cpu> pose({Bt, 1, 2}), yaw({Bt, 1, 1});
    for (std::int64_t b = 0; b < Bt; ++b) {
      pose.at(b, 0, 0) = traj.at(b, 0, 0);
      pose.at(b, 0, 1) = traj.at(b, 0, 1);
      yaw.at(b, 0, 0) = traj.at(b, 0, 2);
    }
    const auto tok = PoseTokenizer::from(cfg_);
    d.pred_pose_idx = tok.poses_to_indices(pose);
    d.pred_yaw_idx = tok.yaws_to_indices(yaw);
    mst_.get_pose_emb(*ctx_, arena_, d.pred_pose_idx, d.pred_yaw_idx, d.pose_emb);
  }

  // The MST over the window (and action): the step's stt_features and pose_emb, in the arena.
  StepDetails<B> condition(const History& h, const NextAction* action, std::int64_t Bt) {
    StepDetails<B> details;
    auto latents = arena_.template take<float>(h.latents.shape());
    BackendTraits<B>::upload_into(*ctx_, h.latents, latents);
    details.stt_features = arena_.template take<float>({Bt, cfg_.tokens_per_frame(), cfg_.n_embd});
    details.pose_emb = arena_.template take<float>({Bt, cfg_.pose_emb_dim()});
    const auto [pose_idx, yaw_idx] = window_indices(h, action);
    mst_.evaluate(*ctx_, arena_, latents, pose_idx, yaw_idx, details.stt_features, details.pose_emb);
    return details;
  }

  // `one` (1, ...) repeated K times along the batch, in the arena (device copies).
  Tensor<float, B> repeat_batch(const Tensor<float, B>& one, std::int64_t K) {
    Shape shape = one.shape();
    shape[0] = K;
    auto out = arena_.template take<float>(shape);
    for (std::int64_t k = 0; k < K; ++k) copy(*ctx_, one.data(), out.data() + k * one.numel(), one.numel());
    return out;
  }

  // Hypothesis k's trajectory noise in row k: the first draw of a plan with hypothesis_seed(seed, k).
  Tensor<float, Cpu> hypothesis_noise(std::int64_t K, std::uint64_t seed) const {
    std::vector<std::uint64_t> seeds(static_cast<std::size_t>(K));
    for (std::int64_t k = 0; k < K; ++k) seeds[static_cast<std::size_t>(k)] = hypothesis_seed(seed, k);
    return NoiseSource::seeded_per_item(seeds).trajectory(traj_noise_shape(K));
  }

  // Arena bytes of plan_hypotheses: one scene's window and conditioning, its K copies and
  // noise, then the larger of the MST and the TrajDiT over K.
  std::size_t hypotheses_bytes(std::int64_t K, const DitSamplers& s) const {
    ArenaCounter<B> persistent;
    persistent.template take<float>({1, cfg_.condition_frames, cfg_.img_tokens(), cfg_.token_dim()});
    for (const std::int64_t rows : {std::int64_t{1}, K}) {
      persistent.template take<float>({rows, cfg_.tokens_per_frame(), cfg_.n_embd});
      persistent.template take<float>({rows, cfg_.pose_emb_dim()});
    }
    persistent.template take<float>(traj_noise_shape(K));
    const nn::JointRows traj_rows{cfg_.tokens_per_frame(), cfg_.traj_len};
    const std::size_t traj = traj_.conditioning_bytes(K, traj_rows) + traj_.sample_bytes(K, traj_rows, s.plan.steps, s.plan.kind);
    return persistent.bytes() + std::max({mst_.evaluate_workspace_bytes(), mst_.pose_emb_workspace_bytes(), traj});
  }

  // Samples one DiT from `noise` over get_schedule(steps, seq_len) with the setting's solver;
  // returns the host result.
  Tensor<float, Cpu> sample(const FluxDiT<B, W>& dit, const StepDetails<B>& d, const Tensor<float, Cpu>& cond_ids,
                            const Tensor<float, Cpu>& target_ids, const Tensor<float, Cpu>& noise,
                            std::int64_t seq_len, const flow::SolverSetting& setting) {
    auto state = arena_.template take<float>(noise.shape());
    BackendTraits<B>::upload_into(*ctx_, noise, state);
    ArenaScope<B> scope(arena_);
    const auto c = dit.prepare(*ctx_, arena_, d.stt_features, cond_ids, target_ids, d.pose_emb);
    dit.sample(*ctx_, arena_, c, flow::get_schedule(setting.steps, seq_len), state, setting.kind);
    Tensor<float, Cpu> out(noise.shape());
    BackendTraits<B>::download_into(*ctx_, state, out);
    return out;
  }

  WorldModelConfig cfg_;
  std::unique_ptr<Context> ctx_ = std::make_unique<Context>();  // a GPU context cannot move; the model can
  Arena<B> arena_;
  SpatialTemporalTransformer<B, W> mst_;
  FluxDiT<B, W> vis_, traj_;
};

}  // namespace model

using model::WorldModel;

}  // namespace epona
