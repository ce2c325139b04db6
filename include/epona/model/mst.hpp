// epona/model/mst.hpp — the Multimodal Spatiotemporal Transformer (models/stt.py
// `SpatialTemporalTransformer`, checkpoint prefix `module.model.`): action and image
// projectors, time_emb, CausalTimeSpaceBlocks (causal time attention, then space attention
// with 2-D RoPE on the image tokens), `evaluate` and `get_pose_emb`. The residual stream,
// projector outputs and results are float32 on every backend (as under the official bf16
// autocast); GEMM inputs/outputs and attention use Activation<B, W> (bf16 on the GPU).
#pragma once

#include <algorithm>
#include <cstdint>
#include <functional>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/core/arena.hpp"
#include "epona/core/backend_capabilities.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config.hpp"
#include "epona/nn/attention.hpp"
#include "epona/nn/blocks/qk_norm_transformer_layer.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/embeddings.hpp"
#include "epona/nn/flops.hpp"
#include "epona/nn/layer_norm.hpp"
#include "epona/nn/linear.hpp"
#include "epona/nn/mlp.hpp"
#include "epona/nn/parameter.hpp"
#include "epona/nn/rope.hpp"

namespace epona::model {

// Sizes of the MST; everything at run time.
struct MstConfig {
  std::int64_t n_embd = 2048, n_head = 16, n_layer = 12;
  std::int64_t condition_frames = 10;  // F (frames of the window)
  std::int64_t latent_h = 16, latent_w = 32, token_dim = 32;
  std::int64_t x_vocab = 128, y_vocab = 128, yaw_vocab = 512;
  std::int64_t fourier_dim = constants::fourier_embed_dim;
  std::int64_t projector_hidden = constants::pose_projector_hidden;
  std::int64_t time_emb_rows = constants::mst_time_emb_rows;
  float fourier_max_period = static_cast<float>(constants::fourier_max_period);
  float rope_theta = static_cast<float>(constants::mst_rope_theta);
  float ln_eps = static_cast<float>(constants::mst_layernorm_eps);

  static MstConfig from(const WorldModelConfig& c) {
    MstConfig m;
    m.n_embd = c.n_embd;
    m.n_head = c.n_head;
    m.n_layer = c.mst_depth();
    m.condition_frames = c.condition_frames;
    m.latent_h = c.latent_h();
    m.latent_w = c.latent_w();
    m.token_dim = c.token_dim();
    m.x_vocab = c.pose_x_vocab_size;
    m.y_vocab = c.pose_y_vocab_size;
    m.yaw_vocab = c.yaw_vocab_size;
    return m;
  }
  std::int64_t head_dim() const { return n_embd / n_head; }
  std::int64_t img_tokens() const { return latent_h * latent_w; }                        // L
  std::int64_t tokens_per_frame() const { return constants::action_tokens + img_tokens(); }  // T
  std::int64_t img_hidden() const { return n_embd / 2; }
  std::int64_t mlp_hidden() const { return 4 * n_embd; }
};

// Action slots inside a frame's token list (and inside the projector outputs).
enum ActionSlot : std::int64_t { kYaw = 0, kPoseX = 1, kPoseY = 2 };

// nn.Sequential(Linear(in, hidden, no bias), GELU, Linear(hidden, C, no bias), LayerNorm(C)).
template <class B, class W>
struct Projector : nn::Bindable<Projector<B, W>> {
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  nn::SequentialMlp<B, W> mlp;  // indices 0 and 2
  nn::LayerNorm<B> norm;        // index 3

  Projector() = default;
  Projector(std::int64_t in, std::int64_t hidden, std::int64_t out, float eps)
      : mlp(in, hidden, out, false, nn::Gelu::Erf), norm(out, eps, true) {}

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    mlp.visit_params(prefix, v);
    norm.visit_params(prefix + "3.", v);
  }
  // x (n, in) -> y (n, C) float32 (LayerNorm's output type under autocast); hidden (n, hidden)
  // and projected (n, C) scratch.
  void operator()(Context& ctx, const Tensor<A, B>& x, Tensor<A, B>& hidden, Tensor<A, B>& projected,
                  Tensor<float, B>& y) const {
    mlp(ctx, x, hidden, projected);
    norm(ctx, projected, y);
  }
};

template <class B, class W>
struct CausalTimeSpaceBlock : nn::Bindable<CausalTimeSpaceBlock<B, W>> {
  nn::QkNormTransformerLayer<B, W> causal_time_block, space_block;

  CausalTimeSpaceBlock() = default;
  explicit CausalTimeSpaceBlock(const MstConfig& c)
      : causal_time_block(c.n_embd, c.mlp_hidden(), c.ln_eps), space_block(c.n_embd, c.mlp_hidden(), c.ln_eps) {}
  template <class V>
  void visit_params(const std::string& p, V& v) {
    causal_time_block.visit_params(p + "causal_time_block.", v);
    space_block.visit_params(p + "space_block.", v);
  }
};

// Called with (batch item, stage, X (F, T, C)) at "tokens_in" and "block{i}_out".
template <class B>
using MstObserver = std::function<void(std::int64_t, const std::string&, const Tensor<float, B>&)>;

template <class B, class W>
class SpatialTemporalTransformer : public nn::Bindable<SpatialTemporalTransformer<B, W>> {
 public:
  using Context = BackendContext<B>;
  using A = Activation<B, W>;
  static constexpr bool kConvertInputs = !std::is_same_v<A, float>;  // float32 inputs need a cast

  SpatialTemporalTransformer() = default;
  explicit SpatialTemporalTransformer(const MstConfig& c)
      : cfg_(c),
        img_projector_(c.token_dim, c.img_hidden(), c.n_embd, c.ln_eps),
        pose_x_projector_(c.fourier_dim, c.projector_hidden, c.n_embd, c.ln_eps),
        pose_y_projector_(c.fourier_dim, c.projector_hidden, c.n_embd, c.ln_eps),
        yaw_projector_(c.fourier_dim, c.projector_hidden, c.n_embd, c.ln_eps) {
    EPONA_CHECK(c.n_head > 0 && c.n_embd % c.n_head == 0, "MST: n_head ", c.n_head, " does not divide n_embd ",
                c.n_embd);
    EPONA_CHECK(c.condition_frames >= 1 && c.condition_frames <= c.time_emb_rows, "MST: condition_frames ",
                c.condition_frames, " outside [1, ", c.time_emb_rows, "]");
    for (std::int64_t i = 0; i < c.n_layer; ++i) blocks_.emplace_back(c);
    rope_ = nn::upload<B>(window_rope_table(c));
  }

  const MstConfig& config() const { return cfg_; }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    v.param(prefix + "time_emb", time_emb_, {cfg_.time_emb_rows, cfg_.n_embd});
    img_projector_.visit_params(prefix + "img_projector.", v);
    pose_x_projector_.visit_params(prefix + "pose_x_projector.", v);
    pose_y_projector_.visit_params(prefix + "pose_y_projector.", v);
    yaw_projector_.visit_params(prefix + "yaw_projector.", v);
    for (std::size_t i = 0; i < blocks_.size(); ++i)
      blocks_[i].visit_params(prefix + "causal_time_space_blocks." + std::to_string(i) + ".", v);
  }

  // Windows folded into one pass of evaluate(): each adds its F·T rows to every product and
  // row pass (about 0.2 GB of bf16 scratch at the shipped size). A window's 5150 rows already
  // fill the GPU's products; folding removes the per-item launches and small tails.
  static constexpr std::int64_t kMaxFoldedItems = 8;
  // Windows per pass, 1 to kMaxFoldedItems (default): fewer bound the scratch; 1 runs the
  // windows one by one. A run-time switch (size the arena after it), so a const model takes it.
  void set_fold_limit(std::int64_t windows) const {
    EPONA_CHECK(windows >= 1 && windows <= kMaxFoldedItems, "MST: windows per pass must be in [1, ", kMaxFoldedItems,
                "], got ", windows);
    fold_limit_ = windows;
  }
  std::int64_t fold_limit() const { return fold_limit_; }
  std::int64_t pass_items(std::int64_t batch) const { return std::clamp<std::int64_t>(batch, 1, fold_limit_); }

  // Arena bytes evaluate() of a batch needs besides its outputs (the scratch of one pass).
  std::size_t evaluate_workspace_bytes(std::int64_t batch = 1) const {
    ArenaCounter<B> counter;
    plan_evaluate(counter, pass_items(batch));
    return counter.bytes();
  }
  std::size_t pose_emb_workspace_bytes(std::int64_t batch = 1) const {
    ArenaCounter<B> counter;
    counter.template take<float>({3, batch, cfg_.n_embd});
    plan_actions(counter, batch);
    return counter.bytes();
  }

  // evaluate(latents, pose_idx, yaw_idx, sample_last=True):
  //   latents (Bt, F, L, token_dim) backend; pose_idx (Bt, F+1, 2), yaw_idx (Bt, F+1, 1) host
  //   -> stt_features (Bt, T, C): the last frame's tokens after the last block;
  //      pose_emb (Bt, 3C): [pose_x, pose_y, yaw] projections of action entry F.
  // Up to kMaxFoldedItems windows run as one pass, frame-major: the residual stream is
  // (F, n·T, C), so a time sequence (item b, token t) and a space sequence (frame f of item b)
  // are each one stride apart, as for one window. With an observer the items run one by one
  // (it sees each item's (F, T, C)).
  void evaluate(Context& ctx, Arena<B>& arena, const Tensor<float, B>& latents, const Tensor<float, Cpu>& pose_idx,
                const Tensor<float, Cpu>& yaw_idx, Tensor<float, B>& stt_features, Tensor<float, B>& pose_emb,
                const MstObserver<B>& observe = {}) const {
    const std::int64_t F = cfg_.condition_frames, T = cfg_.tokens_per_frame(), C = cfg_.n_embd;
    EPONA_CHECK(latents.dim() == 4, "MST latents must be (B, F, L, C_vae), got ", shape_str(latents.shape()));
    const std::int64_t batch = latents.size(0);
    check_shape(latents, {batch, F, cfg_.img_tokens(), cfg_.token_dim}, "MST latents");
    check_shape(pose_idx, {batch, F + 1, 2}, "MST pose indices");
    check_shape(yaw_idx, {batch, F + 1, 1}, "MST yaw indices");
    check_shape(stt_features, {batch, T, C}, "MST stt_features output");
    check_shape(pose_emb, {batch, 3 * C}, "MST pose_emb output");
    const std::int64_t per_pass = observe ? 1 : pass_items(batch);
    for (std::int64_t first = 0; first < batch; first += per_pass) {
      const std::int64_t n = std::min(per_pass, batch - first);
      ArenaScope<B> scope(arena);
      auto s = plan_evaluate(arena, n);
      // On the main queue, before the fork: the side reads it.
      upload_fourier(ctx, s.pose, pose_idx.slice(first, first + n).reshape({n * (F + 1), 2}),
                     yaw_idx.slice(first, first + n).reshape({n * (F + 1), 1}));
      // The pose projectors' twelve small kernels run on the side queue, beside the image projector's.
      side_.fork(ctx);
      project_actions(side_.side(ctx), s.pose, s.actions);
      project_images(ctx, latents.slice(first, first + n), s);
      side_.join(ctx);
      assemble_tokens(ctx, s, n);
      if (observe) observe(first, "tokens_in", s.x);
      for (std::size_t i = 0; i < blocks_.size(); ++i) {
        // Only the last frame of the last block is consumed; an observer sees every frame.
        const bool prune = i + 1 == blocks_.size() && !observe;
        // Every layer's last residual add writes the next layer's ln1 (none after the last).
        const nn::QkNormTransformerLayer<B, W>* next = i + 1 < blocks_.size() ? &blocks_[i + 1].causal_time_block : nullptr;
        if (prune) run_last_block(ctx, blocks_[i], s, i > 0, n);
        else run_block(ctx, blocks_[i], s, i > 0, next, n);
        if (observe) observe(first, "block" + std::to_string(i) + "_out", s.x);
      }
      // The last frame's rows of the n items are their stt_features, in item order.
      auto last = s.x[F - 1];
      copy(ctx, last.data(), stt_features[first].data(), n * T * C);
      for (std::int64_t b = 0; b < n; ++b) {
        auto emb = pose_emb[first + b];
        write_pose_emb(ctx, s.actions, b * (F + 1) + F, emb);
      }
    }
  }

  // get_pose_emb: pose_idx (Bt, 1, 2), yaw_idx (Bt, 1, 1) host -> (Bt, 3C) [pose_x, pose_y, yaw].
  void get_pose_emb(Context& ctx, Arena<B>& arena, const Tensor<float, Cpu>& pose_idx,
                    const Tensor<float, Cpu>& yaw_idx, Tensor<float, B>& pose_emb) const {
    const std::int64_t batch = pose_emb.size(0);
    check_shape(pose_idx, {batch, 1, 2}, "get_pose_emb pose indices");
    check_shape(yaw_idx, {batch, 1, 1}, "get_pose_emb yaw indices");
    check_shape(pose_emb, {batch, 3 * cfg_.n_embd}, "get_pose_emb output");
    if (batch == 0) return;
    ArenaScope<B> scope(arena);
    auto actions = arena.template take<float>({3, batch, cfg_.n_embd});
    auto scratch = plan_actions(arena, batch);
    upload_fourier(ctx, scratch, pose_idx.reshape({batch, 2}), yaw_idx.reshape({batch, 1}));
    project_actions(ctx, scratch, actions);
    for (std::int64_t b = 0; b < batch; ++b) {
      auto emb = pose_emb[b];
      write_pose_emb(ctx, actions, b, emb);
    }
  }

  // FLOPs of one evaluate (batch 1): `executed` counts what runs (the last block computes the
  // last frame only); otherwise what the official code computes (every frame in every block).
  nn::Flops evaluate_flops(bool executed = true) const {
    const double F = double(cfg_.condition_frames), C = double(cfg_.n_embd);
    const double L = double(cfg_.img_tokens()), E = double(cfg_.fourier_dim), P = double(cfg_.projector_hidden);
    const std::int64_t n = cfg_.condition_frames * cfg_.tokens_per_frame(), t = cfg_.tokens_per_frame();
    nn::Flops f{2 * F * L * (double(cfg_.token_dim) * double(cfg_.img_hidden()) + double(cfg_.img_hidden()) * C) +
                    2 * 3 * (F + 1) * (E * P + P * C),
                0};
    const std::int64_t H = cfg_.n_head, d = cfg_.head_dim(), Fi = cfg_.condition_frames;
    for (std::size_t i = 0; i < blocks_.size(); ++i) {
      const auto& blk = blocks_[i];
      if (executed && i + 1 == blocks_.size()) {
        f += blk.causal_time_block.flops(n, t) + blk.space_block.flops(t, t);
        f.attention += nn::attention_flops(t, H, 1, Fi, d) + nn::attention_flops(1, H, t, t, d);
      } else {
        f += blk.causal_time_block.flops(n, n) + blk.space_block.flops(n, n);
        f.attention += nn::attention_flops(t, H, Fi, Fi, d) + nn::attention_flops(Fi, H, t, t, d);
      }
    }
    return f;
  }

 private:
  struct ActionScratch {
    Tensor<A, B> fourier;    // (3, n, E)
    Tensor<A, B> hidden;     // (n, P)
    Tensor<A, B> projected;  // (n, C) before the projector's LayerNorm
  };
  // One pass over n windows (items); item b's rows are b-th in each frame's n·T.
  struct EvaluateScratch {
    Tensor<float, B> actions;       // (3, n·(F+1), C): projector outputs, slots yaw, pose_x, pose_y
    ActionScratch pose;             // the pose projectors' inputs and scratch over n·(F+1) entries
    Tensor<A, B> latents;           // (n·F·L, token_dim) the latents as GEMM input (empty when A is float)
    Tensor<A, B> img_hidden;        // (n·F·L, C/2)
    Tensor<float, B> x;             // (F, n·T, C) residual stream, frame-major
    typename nn::QkNormTransformerLayer<B, W>::Scratch layer;  // (F·n·T) tokens
  };

  template <class Alloc>
  EvaluateScratch plan_evaluate(Alloc& a, std::int64_t n) const {
    const std::int64_t F = cfg_.condition_frames, T = cfg_.tokens_per_frame(), C = cfg_.n_embd;
    const std::int64_t images = n * F * cfg_.img_tokens();
    EvaluateScratch s;
    s.actions = a.template take<float>({3, n * (F + 1), C});
    s.pose = plan_actions(a, n * (F + 1));
    if (kConvertInputs) s.latents = a.template take<A>({images, cfg_.token_dim});
    s.img_hidden = a.template take<A>({images, cfg_.img_hidden()});
    s.x = a.template take<float>({F, n * T, C});
    s.layer = nn::QkNormTransformerLayer<B, W>::plan(a, F * n * T, cfg_.n_embd, cfg_.mlp_hidden());
    return s;
  }
  template <class Alloc>
  ActionScratch plan_actions(Alloc& a, std::int64_t n) const {
    return {a.template take<A>({3, n, cfg_.fourier_dim}), a.template take<A>({n, cfg_.projector_hidden}),
            a.template take<A>({n, cfg_.n_embd})};
  }

  // Coordinates [yaw_idx/yaw_vocab, x_idx/x_vocab, y_idx/y_vocab] -> Fourier features in
  // s.fourier (3, n, E), slot order yaw, pose_x, pose_y; pose_idx (n, 2), yaw_idx (n, 1).
  void upload_fourier(Context& ctx, ActionScratch& s, const Tensor<float, Cpu>& pose_idx,
                      const Tensor<float, Cpu>& yaw_idx) const {
    const std::int64_t n = yaw_idx.size(0), E = cfg_.fourier_dim;
    EPONA_CHECK(s.fourier.size(1) == n, "MST action scratch holds ", s.fourier.size(1), " entries, not ", n);
    Tensor<float, Cpu> coords({3, n}), fourier({3, n, E});
    for (std::int64_t i = 0; i < n; ++i) {
      coords.at(kYaw, i) = yaw_idx.at(i, 0) / static_cast<float>(cfg_.yaw_vocab);
      coords.at(kPoseX, i) = pose_idx.at(i, 0) / static_cast<float>(cfg_.x_vocab);
      coords.at(kPoseY, i) = pose_idx.at(i, 1) / static_cast<float>(cfg_.y_vocab);
    }
    nn::fourier_embed(coords.data(), 3 * n, E, cfg_.fourier_max_period, fourier.data());
    upload_as(ctx, fourier, s.fourier);  // the projectors' GEMMs take it in A (rounded on the host)
  }
  // s.fourier -> actions (3, n, C) through the yaw, pose_x and pose_y projectors.
  void project_actions(Context& ctx, ActionScratch& s, Tensor<float, B>& actions) const {
    const Projector<B, W>* projectors[3] = {&yaw_projector_, &pose_x_projector_, &pose_y_projector_};
    for (std::int64_t slot = 0; slot < 3; ++slot) {
      auto out = actions[slot];
      (*projectors[slot])(ctx, s.fourier[slot], s.hidden, s.projected, out);
    }
  }

  // pose_emb = [pose_x, pose_y, yaw] of action entry `entry`.
  void write_pose_emb(Context& ctx, const Tensor<float, B>& actions, std::int64_t entry, Tensor<float, B>& emb) const {
    const std::int64_t C = cfg_.n_embd;
    const std::int64_t order[3] = {kPoseX, kPoseY, kYaw};
    for (int i = 0; i < 3; ++i) copy(ctx, actions[order[i]][entry].data(), emb.data() + i * C, C);
  }

  // The image projector's two GEMMs, once over all n·F·L tokens of latents (n, F, L, token_dim),
  // into s.layer.u in item order (free until the first block); its LayerNorm is part of
  // assemble_tokens.
  void project_images(Context& ctx, const Tensor<float, B>& latents, EvaluateScratch& s) const {
    const std::int64_t rows = latents.size(0) * cfg_.condition_frames * cfg_.img_tokens();
    auto flat = latents.reshape({rows, cfg_.token_dim});
    if constexpr (kConvertInputs) {
      convert(ctx, flat.data(), s.latents.data(), flat.numel());
      img_projector_.mlp.fc1(ctx, s.latents, s.img_hidden, BackendEpilogue<B>::GeluErf);
    } else {
      img_projector_.mlp.fc1(ctx, flat, s.img_hidden, BackendEpilogue<B>::GeluErf);
    }
    auto projected = s.layer.u.slice(0, rows);
    img_projector_.mlp.fc2(ctx, s.img_hidden, projected);
  }

  // Item b's frame f (rows b·T.. of X[f]) = [yaw, pose_x, pose_y of its entry f, LN(its
  // projected image rows of f)] + time_emb[f], one pass where the backend has it.
  void assemble_tokens(Context& ctx, EvaluateScratch& s, std::int64_t n) const {
    const std::int64_t F = cfg_.condition_frames, T = cfg_.tokens_per_frame(), C = cfg_.n_embd;
    const std::int64_t L = cfg_.img_tokens();
    const auto projected = s.layer.u.slice(0, n * F * L);
    const auto& ln = img_projector_.norm;
    const FrameTokens tokens{F, L, constants::action_tokens, s.actions.size(1), C, ln.eps, n};
    if constexpr (FusedFrameTokens<Context, A>) {
      if (try_assemble_frame_tokens(ctx, projected.data(), s.actions.data(), time_emb_.data(), ln.weight.data(),
                                    ln.bias.data(), s.x.data(), tokens))
        return;
    }
    for (std::int64_t b = 0; b < n; ++b)
      for (std::int64_t f = 0; f < F; ++f) {
        auto frame = s.x[f].slice(b * T, (b + 1) * T);  // (T, C)
        auto image_rows = frame.slice(3, T);            // (L, C)
        const std::int64_t image = (b * F + f) * L, entry = b * (F + 1) + f;
        img_projector_.norm(ctx, projected.slice(image, image + L), image_rows);
        for (std::int64_t slot = 0; slot < 3; ++slot) copy(ctx, s.actions[slot][entry].data(), frame[slot].data(), C);
        add_row_broadcast(ctx, frame.data(), time_emb_[f].data(), T, C);
      }
  }

  // `normed`: s.layer.u holds the time layer's ln1(x) already; `next`: the layer after the block.
  // n items, frame-major (F, n·T, C).
  void run_block(Context& ctx, const CausalTimeSpaceBlock<B, W>& block, EvaluateScratch& s, bool normed,
                 const nn::QkNormTransformerLayer<B, W>* next, std::int64_t n) const {
    const std::int64_t F = cfg_.condition_frames, T = cfg_.tokens_per_frame(), C = cfg_.n_embd;
    const std::int64_t H = cfg_.n_head, d = cfg_.head_dim(), R = n * T;
    auto x = s.x.reshape({F * R, C});
    // (a) time: each of the n·T token positions is a causal sequence over the F frames; no RoPE.
    const nn::PackedAttention time{R, F, H, d, C, R * C, C, R * C, true};
    block.causal_time_block(ctx, x, s.layer, 0, F * R, nullptr, time, normed, &block.space_block);
    // (b) space: each frame of each item is one unmasked sequence of T tokens; RoPE on the image
    // tokens only.
    run_space(ctx, block.space_block, x, s.layer, F * n, next);
  }

  // The last block for the last frame only: its time attention still reads keys and values
  // of every frame (the last frame attends to all of them, so no mask is needed).
  void run_last_block(Context& ctx, const CausalTimeSpaceBlock<B, W>& block, EvaluateScratch& s, bool normed,
                      std::int64_t n) const {
    const std::int64_t F = cfg_.condition_frames, T = cfg_.tokens_per_frame(), C = cfg_.n_embd;
    const std::int64_t H = cfg_.n_head, d = cfg_.head_dim(), R = n * T;
    auto x = s.x.reshape({F * R, C});
    nn::PackedAttention time{R, F, H, d, C, R * C, C, 0, false};
    time.q_len = 1;
    time.q_seq_stride = C;
    // The time layer updates the last frame's rows (of every item): the space layer's whole input.
    block.causal_time_block(ctx, x, s.layer, (F - 1) * R, R, nullptr, time, normed, &block.space_block);
    auto last = s.x[F - 1];
    run_space(ctx, block.space_block, last, s.layer, n, nullptr);
  }

  // Space attention over `frames` consecutive frames of x (frames·T, C).
  // Its ln1 is in s.u already (the time layer's last residual add wrote it).
  void run_space(Context& ctx, const nn::QkNormTransformerLayer<B, W>& layer, Tensor<float, B>& x, typename nn::QkNormTransformerLayer<B, W>::Scratch& s,
                 std::int64_t frames, const nn::QkNormTransformerLayer<B, W>* next) const {
    const std::int64_t T = cfg_.tokens_per_frame(), C = cfg_.n_embd, H = cfg_.n_head, d = cfg_.head_dim();
    const nn::PackedAttention space{frames, T, H, d, T * C, C, T * C, C, false};
    // One pass over all frames' tokens: the table leaves the action tokens unrotated
    // (cos 1, sin 0 rotate exactly to themselves).
    layer(ctx, x, s, 0, frames * T, &rope_, space, true, next);
  }

  // compute_axial_cis for the image tokens of every frame of a pass (kMaxFoldedItems windows;
  // every frame's table is the same), identity rows (cos 1, sin 0) for the action tokens:
  // (kMaxFoldedItems·F·T, head_dim/2).
  static nn::RopeTable<Cpu> window_rope_table(const MstConfig& c) {
    const auto image = nn::axial_rope_table(c.head_dim(), c.latent_h, c.latent_w, c.rope_theta);
    const std::int64_t T = c.tokens_per_frame(), pairs = image.pairs(), frames = kMaxFoldedItems * c.condition_frames;
    const std::int64_t rows = frames * T;
    nn::RopeTable<Cpu> t{Tensor<float, Cpu>::full({rows, pairs}, 1.0f), Tensor<float, Cpu>::zeros({rows, pairs})};
    for (std::int64_t f = 0; f < frames; ++f) {
      const std::int64_t first = (f * T + constants::action_tokens) * pairs;
      std::copy_n(image.cos.data(), image.cos.numel(), t.cos.data() + first);
      std::copy_n(image.sin.data(), image.sin.numel(), t.sin.data() + first);
    }
    return t;
  }

  MstConfig cfg_;
  Tensor<float, B> time_emb_;  // (rows, C)
  Projector<B, W> img_projector_, pose_x_projector_, pose_y_projector_, yaw_projector_;
  std::vector<CausalTimeSpaceBlock<B, W>> blocks_;
  nn::RopeTable<B> rope_;  // (kMaxFoldedItems·F·T, head_dim/2): every frame's rows, the action tokens unrotated
  mutable typename BackendTraits<B>::SideQueue side_;  // the pose projectors' queue (a second GPU stream)
  mutable std::int64_t fold_limit_ = kMaxFoldedItems;
};

}  // namespace epona::model
