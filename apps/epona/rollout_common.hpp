// apps/epona/rollout_common.hpp — the rollout loop that generate and eval share: each step
// predicts the next frame from the sliding window, driven by given actions (one per step) or by
// the model's own plan (waypoint 0), and generated latents are decoded as they complete (clips of
// the DC-AE's temporal length, or frame by frame) into a FrameConsumer.
#pragma once

#include <algorithm>
#include <cstdint>
#include <future>
#include <memory>
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

// One scene of a batched rollout: its window (batch 1), its seed, its actions (one per step, when
// the plan's steps are driven) and where its frames go.
struct RolloutItem {
  History window;
  std::uint64_t seed = 0;
  std::optional<io::PoseSequence> actions;
  FrameConsumer* sink = nullptr;
};

// The windows of one scene each (batch 1) as one batch, in order.
inline History stack_windows(const std::vector<const History*>& windows) {
  const auto n = static_cast<std::int64_t>(windows.size());
  const auto stack = [n, &windows](Tensor<float> History::*part) {
    const Tensor<float>& first = windows.front()->*part;
    Shape shape = first.shape();
    shape[0] = n;
    Tensor<float> out(shape);
    for (std::int64_t b = 0; b < n; ++b) {
      const Tensor<float>& one = windows[static_cast<std::size_t>(b)]->*part;
      EPONA_CHECK(one.shape() == first.shape(), "internal: windows of different shapes in one batch");
      std::copy_n(one.data(), one.numel(), out[b].data());
    }
    return out;
  };
  return {stack(&History::latents), stack(&History::rel_pose), stack(&History::rel_yaw)};
}

// Item b's actions at step i of every item, as one batched action (Bt, 1, ·).
inline NextAction batch_action_at(const std::vector<RolloutItem>& items, std::size_t i) {
  const auto n = static_cast<std::int64_t>(items.size());
  NextAction a{Tensor<float>({n, 1, 2}), Tensor<float>({n, 1, 1})};
  for (std::int64_t b = 0; b < n; ++b) {
    const io::PoseSequence& p = *items[static_cast<std::size_t>(b)].actions;
    a.rel_pose.at(b, 0, 0) = p.x[i], a.rel_pose.at(b, 0, 1) = p.y[i], a.rel_yaw.at(b, 0, 0) = p.yaw[i];
  }
  return a;
}

// Rolls Bt scenes out together: one world-model step over the batch per frame, item b's noise from
// its own seed (NoiseSource::seeded_per_item: what a rollout of it alone draws), each window slid
// after each step and each item's frames decoded into its sink as soon as its clip is complete.
// With one item this is the single rollout. The plan's seed and actions are the items'.
inline std::vector<RolloutLog> roll_out_batch(Engine& engine, cpu::Context& ctx, std::vector<RolloutItem> items,
                                              const WorldModelConfig& wc, const RolloutPlan& p, const Console& con) {
  EPONA_CHECK(!items.empty(), "internal: a batched rollout of no scenes");
  const bool driven = items.front().actions.has_value();
  std::vector<std::uint64_t> seeds;
  std::vector<const History*> windows;
  for (const auto& item : items) {
    EPONA_CHECK(item.actions.has_value() == driven && (!driven || std::int64_t(item.actions->size()) >= p.frames),
                "internal: the scenes of a batched rollout differ in their actions");
    seeds.push_back(item.seed), windows.push_back(&item.window);
  }
  const std::int64_t W = driven ? 1 : wc.traj_len, L = wc.img_tokens(), C = wc.token_dim();
  std::vector<RolloutLog> logs;
  std::vector<std::unique_ptr<FrameDecoder>> decoders;
  std::vector<std::vector<Tensor<float>>> pending(items.size());
  for (auto& item : items) {
    logs.push_back({Tensor<float>({p.frames, W, 3}), {}, p.keep_latents ? Tensor<float>({p.frames, L, C}) : Tensor<float>()});
    decoders.push_back(std::make_unique<FrameDecoder>(engine, ctx, wc, *item.sink));
  }
  // One decode in flight at a time: the DC-AE's context is shared by the items' decoders.
  const auto decode = [&](std::size_t b, bool is_video) {
    for (std::size_t o = 0; o < decoders.size(); ++o)
      if (o != b) decoders[o]->finish();
    decoders[b]->decode(pending[b], is_video);
    pending[b].clear();
  };
  History window = stack_windows(windows);
  NoiseSource noise = NoiseSource::seeded_per_item(seeds);
  Progress bar(con, "generate", p.frames, "frame");
  for (std::int64_t i = 0; i < p.frames; ++i) {
    const auto act = driven ? std::optional(batch_action_at(items, std::size_t(i))) : std::nullopt;
    const StepResult r = engine.step(window, act ? &*act : nullptr, p.samplers, noise);
    Tensor<float> used({std::int64_t(items.size()), W, 3});  // what drove this step, per item
    for (std::size_t b = 0; b < items.size(); ++b) {
      const auto bi = static_cast<std::int64_t>(b);
      float* u = used[bi].data();
      if (act) {
        u[0] = act->rel_pose.at(bi, 0, 0), u[1] = act->rel_pose.at(bi, 0, 1), u[2] = act->rel_yaw.at(bi, 0, 0);
      } else {
        std::copy_n(r.trajectory[bi].data(), W * 3, u);
      }
      std::copy_n(u, W * 3, logs[b].steps[i].data());
      logs[b].motions.x.push_back(u[0]), logs[b].motions.y.push_back(u[1]), logs[b].motions.yaw.push_back(u[2]);
      if (p.keep_latents) std::copy_n(r.latent[bi].data(), L * C, logs[b].latents[i].data());
      pending[b].push_back(r.latent.slice(bi, bi + 1).clone());
    }
    model::slide_window(window, r.latent, used);
    for (std::size_t b = 0; b < items.size(); ++b)
      if (static_cast<std::int64_t>(pending[b].size()) == p.clip_len) decode(b, p.clip_len > 1);
    bar.advance();
  }
  for (std::size_t b = 0; b < items.size(); ++b) decode(b, false);  // an incomplete last clip: frame by frame (test_nuplan.py)
  for (auto& d : decoders) d->finish();
  return logs;
}

// Runs the rollout of one scene from `window` (the official draw order from the plan's seed), the
// window slid after each step, frames decoded into `sink` as soon as a clip is complete.
inline RolloutLog roll_out(Engine& engine, cpu::Context& ctx, History window, const WorldModelConfig& wc,
                           const RolloutPlan& p, FrameConsumer& sink, const Console& con) {
  std::vector<RolloutItem> one;
  one.push_back({std::move(window), p.seed, p.actions, &sink});
  return std::move(roll_out_batch(engine, ctx, std::move(one), wc, p, con).front());
}

}  // namespace epona::app
