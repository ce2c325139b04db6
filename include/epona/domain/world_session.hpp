// epona/domain/world_session.hpp — an interactive driving session over a loaded world model and
// DC-AE: reset() encodes the last F frames once; each step() plans (or takes the given action),
// predicts the next latent, decodes it to a frame and slides the window by one — the step of the
// CLI's rollout (apps/epona/rollout_common.hpp) and of model::rollout, one call at a time, with
// one noise generator for the whole session (the official draw order). Any backend: the window,
// the actions and every result stay on the host (the WorldModel's interface); only the DC-AE's
// images and latents cross to the backend's memory, as the CLI's engine does (apps/epona/engine.hpp).
#pragma once

#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>
#include <type_traits>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cpu/context.hpp"
#include "epona/domain/poses.hpp"
#include "epona/io/image.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona {

// The motion from the last window frame into the next one: metres forward, metres left, degrees
// (left turn positive) — one row of a poses file, waypoint 0 of a plan.
struct Motion {
  float x = 0, y = 0, yaw = 0;
};

// A one-scene action (1, 1, 2) + (1, 1, 1) holding `m`: written into `a`'s tensors, or new ones.
inline void set_action(NextAction& a, const Motion& m) {
  a.rel_pose.data()[0] = m.x, a.rel_pose.data()[1] = m.y;
  a.rel_yaw.data()[0] = m.yaw;
}
inline NextAction action_of(const Motion& m) {
  NextAction a{Tensor<float, Cpu>({1, 1, 2}), Tensor<float, Cpu>({1, 1, 1})};
  set_action(a, m);
  return a;
}

// What one session step made.
struct SessionStep {
  io::Image frame;                // the generated frame, 8-bit RGB, image_h x image_w (decoded alone)
  Tensor<float, Cpu> trajectory;  // (traj_len, 3) the plan that drove the step; empty when an action was given
  Motion motion;                  // the motion into the new frame: the action, or waypoint 0 of the plan
  Tensor<float, Cpu> latent;      // (L, C) the new frame's latent tokens
};

namespace model {

// The world model's window (batch 1) from encoded frames (F, C, h, w) and their motions. The
// window's first frame gets no motion: the official code makes a window's motions with
// get_rel_pose of its own poses, which gives the first frame the identity, in training and in its
// planning test (scripts/test/test_traj.py), so the model has never seen a motion there (a real
// one there cost the bundled model 60% more planning error at 1 s; docs/evaluation.md).
template <class Ctx>
History make_window(Ctx& ctx, const Tensor<float, Cpu>& latents, const io::PoseSequence& poses) {
  const Tensor<float, Cpu> tokens = latent_to_tokens(ctx, latents);  // (F, L, C)
  History h{tokens.reshape({1, tokens.size(0), tokens.size(1), tokens.size(2)}), poses.pose_tensor(), poses.yaw_tensor()};
  if (h.rel_pose.numel() > 0) h.rel_pose.data()[0] = h.rel_pose.data()[1] = h.rel_yaw.data()[0] = 0.0f;
  return h;
}

// Holds references to a loaded WorldModel and Dcae (the caller keeps them alive; several sessions
// may share one model, one call at a time) and owns the window of the last F frames.
//
// No reload and no reallocation of the per-step state between steps: the window's three tensors
// are allocated once by reset() and slid in place (shift_window with from == to); the action
// tensors are allocated once; the world model's arena is sized by the first step and reused
// (WorldModel::reserve_arena grows it only for a larger batch or more sampling steps, and a
// session keeps both fixed; arena_capacity() shows it). Each step's results (trajectory, latent,
// frame) are new tensors the caller keeps, and the DC-AE decoder allocates its feature maps per
// call (Dcae has no arena; on a device backend also the latent it uploads and the frame it downloads).
//
// On a device backend (Cuda) the DC-AE runs on the world model's context (its stream), and the
// latent layout changes (tokens <-> NCHW) run on the host, where the window lives.
template <class B = Cpu, class W = float>
class WorldSession {
 public:
  WorldSession(WorldModel<B, W>& world, const Dcae<B, W>& dcae, const SampleOptions& options = {})
      : world_(world), dcae_(dcae), host_(make_host_context()), options_(options),
        samplers_(world.samplers_of(options)), noise_(WorldModel<B, W>::noise_for(options)),
        action_(action_of({})), used_({1, 1, 3}) {
    EPONA_CHECK(dcae.config().latent_channels == world.config().token_dim(), "WorldSession: the DC-AE's ",
                dcae.config().latent_channels, " latent channels differ from the world model's ",
                world.config().token_dim());
  }

  const WorldModelConfig& config() const { return world_.config(); }
  std::int64_t frames_needed() const { return config().condition_frames; }

  // Starts from the last F frames (8-bit RGB at the model's image size, oldest first) and the
  // motion into each (poses[i] into frames[i]; the first is not used, see make_window). Encodes
  // the frames once and restarts the noise generator from the session's options.
  void reset(const std::vector<io::Image>& frames, const io::PoseSequence& poses) {
    const auto& c = config();
    EPONA_CHECK(static_cast<std::int64_t>(frames.size()) == c.condition_frames, "WorldSession::reset: ",
                frames.size(), " frame(s) given; the model needs ", c.condition_frames, " (condition_frames)");
    for (std::size_t i = 0; i < frames.size(); ++i)
      EPONA_CHECK(frames[i].height == c.image_h && frames[i].width == c.image_w, "WorldSession::reset: frame ", i,
                  " is ", frames[i].height, "x", frames[i].width, "; the model takes ", c.image_h, "x", c.image_w);
    check_poses(poses);
    const Tensor<float, B> images = BackendTraits<B>::upload(io::images_to_tensor(frames));
    reset_latents(host_tensor(world_.context(), dcae_.encode(world_.context(), images)), poses);
  }

  // The same from frames already encoded: latents (F, C, h, w) as Dcae::encode gives them.
  void reset_latents(const Tensor<float, Cpu>& latents, const io::PoseSequence& poses) {
    const auto& c = config();
    check_shape(latents, {c.condition_frames, c.token_dim(), c.latent_h(), c.latent_w()}, "WorldSession latents");
    check_poses(poses);
    History h = make_window(host(), latents, poses);
    world_.validate(h, nullptr, samplers_);  // non-finite latents
    window_ = History{h.latents.clone(), h.rel_pose.clone(), h.rel_yaw.clone()};  // owned: slid in place
    noise_ = WorldModel<B, W>::noise_for(options_);
    steps_ = 0;
  }

  // One autoregressive step: without an action the model plans and drives waypoint 0 of its plan
  // (test_free.py); with one, it is the motion into the new frame (generate_gt_pose_gt_yaw).
  SessionStep step(const std::optional<Motion>& action = std::nullopt) {
    EPONA_CHECK(!window_.latents.empty(), "WorldSession::step: no window yet; call reset() with the first ",
                frames_needed(), " frames and poses");
    if (action) {
      EPONA_CHECK(std::isfinite(action->x) && std::isfinite(action->y) && std::isfinite(action->yaw),
                  "WorldSession::step: the action (", action->x, ", ", action->y, ", ", action->yaw,
                  ") has a non-finite value");
      set_action(action_, *action);
    }
    SessionStep out;
    StepResult r = world_.run_step(window_, action ? &action_ : nullptr, true, samplers_, noise_, {});
    out.motion = action ? *action : Motion{r.trajectory.at(0, 0, 0), r.trajectory.at(0, 0, 1), r.trajectory.at(0, 0, 2)};
    used_.data()[0] = out.motion.x, used_.data()[1] = out.motion.y, used_.data()[2] = out.motion.yaw;
    out.frame = decode_frame(r.latent);  // before the slide: a failed decode leaves the window as it was
    shift_window(window_, window_, r.latent, used_);
    if (!action) out.trajectory = r.trajectory.reshape({r.trajectory.size(1), r.trajectory.size(2)});
    out.latent = r.latent.reshape({r.latent.size(1), r.latent.size(2)});
    ++steps_;
    return out;
  }

  // The window the next step sees: latents (1, F, L, C), rel_pose (1, F, 2), rel_yaw (1, F, 1).
  const History& window() const { return window_; }
  std::int64_t steps_taken() const { return steps_; }
  // The world model's workspace: stays the same from the first step on (see the class comment).
  std::size_t arena_capacity() const { return world_.arena_capacity(); }

 private:
  void check_poses(const io::PoseSequence& poses) const {
    EPONA_CHECK(static_cast<std::int64_t>(poses.size()) == frames_needed() && poses.y.size() == poses.size() &&
                    poses.yaw.size() == poses.size(),
                "WorldSession::reset: ", poses.size(), " pose(s) given; the model needs ", frames_needed(),
                " (one motion per frame)");
    for (std::size_t i = 0; i < poses.size(); ++i)
      EPONA_CHECK(std::isfinite(poses.x[i]) && std::isfinite(poses.y[i]) && std::isfinite(poses.yaw[i]),
                  "WorldSession::reset: pose ", i, " (", poses.x[i], ", ", poses.y[i], ", ", poses.yaw[i],
                  ") has a non-finite value");
  }

  // Tokens (1, L, C) -> the frame, decoded alone (the CLI's --decode frame).
  io::Image decode_frame(const Tensor<float, Cpu>& tokens) {
    const auto& c = config();
    const Tensor<float, Cpu> latent = tokens_to_latent(host(), tokens, c.latent_h(), c.latent_w());
    const Tensor<float, B> image = dcae_.decode(world_.context(), BackendTraits<B>::upload(latent), false);
    return io::tensor_to_image(host_tensor(world_.context(), image), 0);
  }

  // The CPU's own context (its thread count); a device backend gets a host context of its own,
  // made with the process's current thread count (making a cpu::Context sets it process-wide).
  static std::unique_ptr<cpu::Context> make_host_context() {
    if constexpr (std::is_same_v<B, Cpu>)
      return nullptr;
    else
      return std::make_unique<cpu::Context>(Eigen::nbThreads());
  }
  cpu::Context& host() {
    if constexpr (std::is_same_v<B, Cpu>)
      return world_.context();
    else
      return *host_;
  }

  WorldModel<B, W>& world_;
  const Dcae<B, W>& dcae_;
  std::unique_ptr<cpu::Context> host_;  // null on the CPU (host() is the world model's context)
  SampleOptions options_;
  DitSamplers samplers_;
  NoiseSource noise_;
  History window_;
  NextAction action_;      // (1, 1, 2), (1, 1, 1): the given action, rewritten each step
  Tensor<float, Cpu> used_;  // (1, 1, 3): the motion that drove the step, for the slide
  std::int64_t steps_ = 0;
};

}  // namespace model

using model::WorldSession;

}  // namespace epona
