// epona/model/rollout.hpp — autoregressive rollout with self-predicted actions
// (scripts/test/test_free.py): each step samples a trajectory and the next latent, then the
// window slides: latents = cat(latents[1:F], new), actions = cat(actions[1:F], waypoint 0)
// — the official window of F+1 actions is cat(rel_pose[:, 1:F], p, p). No ground truth
// enters after the first step.
#pragma once

#include <cstdint>
#include <cstring>
#include <functional>
#include <type_traits>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/model/world_model.hpp"

namespace epona {

struct RolloutOptions {
  std::int64_t frames = 0;  // frames to generate (test_free.py generates 54)
  SampleOptions sample;     // steps, and the noise of every step (seed or supplied (frames, ...))
};

template <class B>
struct RolloutFrame {
  std::int64_t index = 0;
  const StepResult& result;           // trajectory (Bt, traj_len, 3) metres/degrees, latent (Bt, L, C)
  const StepDetails<B>& details;      // MST features, the pose embedding fed to the VisDiT, indices
  const History& window;              // the window after the slide (what the next step sees)
  Tensor<float, Cpu> rel_pose_window; // (Bt, F+1, 2) test_free's rel_pose after the update
  Tensor<float, Cpu> rel_yaw_window;  // (Bt, F+1, 1)
};

struct RolloutResult {
  Tensor<float, Cpu> trajectories;  // (frames, Bt, traj_len, 3)
  Tensor<float, Cpu> latents;       // (frames, Bt, L, C)
  History window;                   // the final window
};

namespace model {

// Drops the oldest frame of `from` into `to` (same shapes; `to` may be `from`: the slide is then
// in place, no allocation): latents += new latent, actions += waypoint 0 of the trajectory.
inline void shift_window(const History& from, History& to, const Tensor<float, Cpu>& latent,
                         const Tensor<float, Cpu>& trajectory) {
  const std::int64_t Bt = from.latents.size(0), F = from.latents.size(1);
  const std::int64_t frame = from.latents.numel() / (Bt * F);
  for (std::int64_t b = 0; b < Bt; ++b) {
    std::memmove(to.latents[b].data(), from.latents[b][1].data(), sizeof(float) * (F - 1) * frame);
    std::memcpy(to.latents[b][F - 1].data(), latent[b].data(), sizeof(float) * frame);
    for (std::int64_t f = 0; f + 1 < F; ++f) {  // ascending: reads f + 1 before an in-place write reaches it
      to.rel_pose.at(b, f, 0) = from.rel_pose.at(b, f + 1, 0);
      to.rel_pose.at(b, f, 1) = from.rel_pose.at(b, f + 1, 1);
      to.rel_yaw.at(b, f, 0) = from.rel_yaw.at(b, f + 1, 0);
    }
    to.rel_pose.at(b, F - 1, 0) = trajectory.at(b, 0, 0);
    to.rel_pose.at(b, F - 1, 1) = trajectory.at(b, 0, 1);
    to.rel_yaw.at(b, F - 1, 0) = trajectory.at(b, 0, 2);
  }
}

// The same into new tensors: the caller's window may share its storage with other tensors.
inline void slide_window(History& h, const Tensor<float, Cpu>& latent, const Tensor<float, Cpu>& trajectory) {
  History next{Tensor<float, Cpu>(h.latents.shape()), Tensor<float, Cpu>(h.rel_pose.shape()),
               Tensor<float, Cpu>(h.rel_yaw.shape())};
  shift_window(h, next, latent, trajectory);
  h = std::move(next);
}

// The official F+1 window: the F actions followed by a copy of the last (the placeholder).
inline Tensor<float, Cpu> with_placeholder(const Tensor<float, Cpu>& actions) {
  const std::int64_t Bt = actions.size(0), F = actions.size(1), k = actions.size(2);
  Tensor<float, Cpu> w({Bt, F + 1, k});
  for (std::int64_t b = 0; b < Bt; ++b) {
    std::memcpy(w[b].data(), actions[b].data(), sizeof(float) * F * k);
    std::memcpy(w[b][F].data(), actions[b][F - 1].data(), sizeof(float) * k);
  }
  return w;
}

template <class B, class W>
RolloutResult rollout(WorldModel<B, W>& wm, History window, const RolloutOptions& opt,
                      const std::type_identity_t<std::function<void(const RolloutFrame<B>&)>>& on_frame = {}) {
  EPONA_CHECK(opt.frames >= 1 && opt.frames <= constants::max_rollout_frames, "rollout frames must be in [1, ",
              constants::max_rollout_frames, "], got ", opt.frames);
  const DitSamplers samplers = wm.samplers_of(opt.sample);
  const std::int64_t Bt = wm.validate(window, nullptr, samplers);
  NoiseSource noise = WorldModel<B, W>::noise_for(opt.sample);
  noise.require(opt.frames, wm.traj_noise_shape(Bt), opt.frames, wm.latent_noise_shape(Bt));
  const auto& cfg = wm.config();
  RolloutResult out{Tensor<float, Cpu>({opt.frames, Bt, cfg.traj_len, constants::traj_token_size}),
                    Tensor<float, Cpu>({opt.frames, Bt, cfg.img_tokens(), cfg.token_dim()}), {}};
  for (std::int64_t i = 0; i < opt.frames; ++i) {
    StepDetails<B> details;
    const StepResult r = wm.run_step(window, nullptr, true, samplers, noise, [&](const StepDetails<B>& d) { details = d; });
    std::memcpy(out.trajectories[i].data(), r.trajectory.data(), r.trajectory.nbytes());
    std::memcpy(out.latents[i].data(), r.latent.data(), r.latent.nbytes());
    slide_window(window, r.latent, r.trajectory);
    if (on_frame)
      on_frame(RolloutFrame<B>{i, r, details, window, with_placeholder(window.rel_pose), with_placeholder(window.rel_yaw)});
  }
  out.window = std::move(window);
  return out;
}

}  // namespace model

using model::rollout;

}  // namespace epona
