// apps/epona/rollout_common.hpp — the rollout loop that generate and eval share: each step
// predicts the next frame from the sliding window, driven by given actions (one per step) or by
// the model's own plan (waypoint 0), and generated latents are decoded as they complete (clips of
// the DC-AE's temporal length, or frame by frame) into a FrameConsumer.
#pragma once

#include <algorithm>
#include <cstdint>
#include <future>
#include <optional>
#include <vector>

#include "console.hpp"
#include "engine.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cpu/context.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/world_session.hpp"
#include "epona/io/image.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"

namespace epona::app {

// Where decoded frames go (files for generate, comparisons for eval).
class FrameConsumer {
 public:
  virtual ~FrameConsumer() = default;
  virtual void put(const io::Image& img) = 0;
};

// Generated latents (tokens (1, L, C) each) as one latent tensor (n, C, h, w).
inline Tensor<float> latent_group(cpu::Context& ctx, const WorldModelConfig& w, const std::vector<Tensor<float>>& tokens) {
  const std::int64_t L = w.img_tokens(), C = w.token_dim(), n = static_cast<std::int64_t>(tokens.size());
  Tensor<float> group({n, L, C});
  for (std::int64_t i = 0; i < n; ++i) std::copy_n(tokens[static_cast<std::size_t>(i)].data(), L * C, group[i].data());
  return tokens_to_latent(ctx, group, w.latent_h(), w.latent_w());
}

// Decodes groups of generated latents (a temporal clip, or frame by frame) into a sink, in order.
// On a GPU (Engine::decodes_beside_steps) a group decodes on a worker thread while the next
// steps sample: the next step needs the latent, not the picture, so a frame's decode overlaps the
// following frame's sampling (issue #40). The frames and their order are the same either way.
class FrameDecoder {
 public:
  FrameDecoder(Engine& engine, cpu::Context& ctx, const WorldModelConfig& w, FrameConsumer& sink)
      : engine_(engine), ctx_(ctx), w_(w), sink_(sink), beside_(engine.decodes_beside_steps()) {}
  FrameDecoder(const FrameDecoder&) = delete;
  FrameDecoder& operator=(const FrameDecoder&) = delete;
  ~FrameDecoder() {
    if (running_.valid()) running_.wait();  // an error on the way out: the worker may not outlive us
  }

  void decode(const std::vector<Tensor<float>>& tokens, bool is_video) {
    if (tokens.empty()) return;
    Tensor<float> latents = latent_group(ctx_, w_, tokens);
    finish();
    if (!beside_) return put(engine_.decode(latents, is_video));
    running_ = std::async(std::launch::async, [this, latents = std::move(latents), is_video] {
      return engine_.decode(latents, is_video);
    });
  }
  // Waits for the group in flight and hands its frames to the sink.
  void finish() {
    if (running_.valid()) put(running_.get());
  }

 private:
  void put(const Tensor<float>& images) {
    for (std::int64_t i = 0; i < images.size(0); ++i) sink_.put(io::tensor_to_image(images, i));
  }
  Engine& engine_;
  cpu::Context& ctx_;
  const WorldModelConfig& w_;
  FrameConsumer& sink_;
  bool beside_;
  std::future<Tensor<float>> running_;
};

inline NextAction action_at(const io::PoseSequence& p, std::size_t i) { return action_of({p.x[i], p.y[i], p.yaw[i]}); }

// What drives a rollout, and what it keeps.
struct RolloutPlan {
  std::int64_t frames = 0, clip_len = 1;  // clip_len: latents decoded together
  DitSamplers samplers;                   // each DiT's solver and steps
  std::uint64_t seed = 0;
  std::optional<io::PoseSequence> actions;  // one per step; none: self-predicted
  bool keep_latents = false;
};

// What drove each step and what it made.
struct RolloutLog {
  Tensor<float> steps;       // (N, W, 3): each step's plan (W = traj_len) or its given action (W = 1)
  io::PoseSequence motions;  // the motion into each generated frame (waypoint 0 / the action)
  Tensor<float> latents;     // (N, L, C) when kept
};

// Runs the rollout from `window`: one noise generator for all steps (the official draw order),
// the window slid after each step, frames decoded into `sink` as soon as a clip is complete.
inline RolloutLog roll_out(Engine& engine, cpu::Context& ctx, History window, const WorldModelConfig& wc,
                           const RolloutPlan& p, FrameConsumer& sink, const Console& con) {
  const std::int64_t W = p.actions ? 1 : wc.traj_len;
  RolloutLog log{Tensor<float>({p.frames, W, 3}), {},
                 p.keep_latents ? Tensor<float>({p.frames, wc.img_tokens(), wc.token_dim()}) : Tensor<float>()};
  std::vector<Tensor<float>> pending;
  FrameDecoder decoder(engine, ctx, wc, sink);
  NoiseSource noise = NoiseSource::seeded(p.seed);
  Progress bar(con, "generate", p.frames, "frame");
  for (std::int64_t i = 0; i < p.frames; ++i) {
    const auto act = p.actions ? std::optional(action_at(*p.actions, std::size_t(i))) : std::nullopt;
    const StepResult r = engine.step(window, act ? &*act : nullptr, p.samplers, noise);
    const Tensor<float> used = log.steps[i].reshape({1, W, 3});  // what drove this step
    if (act) {
      used.data()[0] = act->rel_pose.data()[0], used.data()[1] = act->rel_pose.data()[1];
      used.data()[2] = act->rel_yaw.data()[0];
    } else {
      std::copy_n(r.trajectory.data(), used.numel(), used.data());
    }
    log.motions.x.push_back(used.data()[0]), log.motions.y.push_back(used.data()[1]);
    log.motions.yaw.push_back(used.data()[2]);
    if (p.keep_latents) std::copy_n(r.latent.data(), r.latent.numel(), log.latents[i].data());
    model::slide_window(window, r.latent, used);
    pending.push_back(r.latent);
    if (static_cast<std::int64_t>(pending.size()) == p.clip_len) {
      decoder.decode(pending, p.clip_len > 1);
      pending.clear();
    }
    bar.advance();
  }
  decoder.decode(pending, false);  // an incomplete last clip: frame by frame (test_nuplan.py)
  decoder.finish();
  return log;
}

}  // namespace epona::app
