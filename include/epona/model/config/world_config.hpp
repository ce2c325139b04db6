// epona/model/config/world_config.hpp — every hyper-parameter of the Epona world model (MST +
// VisDiT + TrajDiT, mirrors the official `configs/dit_config_dcae_*.py`), its derived sizes and
// validate(). Its parameter counts come from the parameter tree (model/parameter_counts.hpp).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>

#include "epona/model/config/constants.hpp"
#include "epona/model/config/problems.hpp"

namespace epona {

// ------------------------------------------------------------------------------------------
// World model: MST (module.model.), VisDiT (module.dit.), TrajDiT (module.traj_dit.).
// Default-constructed = the shipped model (configs/dit_config_dcae_nuplan.py).
struct WorldModelConfig {
  std::int64_t image_h = 512, image_w = 1024;  // image_size (H, W)
  std::int64_t downsample_size = 32;           // DC-AE spatial factor
  std::int64_t patch_size = 1;
  std::int64_t vae_embed_dim = 32;             // latent channels per token
  std::int64_t condition_frames = 10;          // F: window of past frames
  std::int64_t block_size = 1;                 // must be 1 for inference
  std::array<std::int64_t, 3> n_layer = {12, 6, 6};  // MST blocks, VisDiT double, VisDiT single
  std::int64_t n_head = 16, n_embd = 2048;           // MST
  std::int64_t n_embd_dit = 2048, n_head_dit = 16;   // VisDiT
  std::array<std::int64_t, 3> axes_dim_dit = {16, 56, 56};
  std::array<std::int64_t, 2> n_layer_traj = {1, 1};  // TrajDiT double, single
  std::int64_t n_embd_dit_traj = 1024, n_head_dit_traj = 8;
  std::array<std::int64_t, 3> axes_dim_dit_traj = {16, 56, 56};
  std::int64_t traj_len = 15;
  std::int64_t pose_x_vocab_size = 128, pose_y_vocab_size = 128, yaw_vocab_size = 512;
  double pose_x_bound = 50.0, pose_y_bound = 10.0, yaw_bound = 12.0;  // metres, metres, degrees
  std::int64_t num_sampling_steps = 100;

  bool operator==(const WorldModelConfig&) const = default;

  // ---- derived sizes ----
  std::int64_t latent_h() const { return image_h / downsample_size / patch_size; }
  std::int64_t latent_w() const { return image_w / downsample_size / patch_size; }
  std::int64_t img_tokens() const { return latent_h() * latent_w(); }  // L
  std::int64_t tokens_per_frame() const { return img_tokens() + constants::action_tokens; }  // L + 3
  std::int64_t token_dim() const { return vae_embed_dim * patch_size * patch_size; }
  // MST: the flattened (F, L+3) token count (the official `block_size` attribute of the MST).
  std::int64_t mst_sequence_tokens() const { return condition_frames * tokens_per_frame(); }
  std::int64_t mst_depth() const { return n_layer[0]; }
  std::int64_t mst_head_dim() const { return n_embd / n_head; }
  std::int64_t mst_img_projector_hidden() const { return n_embd / 2; }
  std::int64_t pose_emb_dim() const { return constants::action_tokens * n_embd; }  // VisDiT y
  std::int64_t vis_double_blocks() const { return n_layer[1]; }
  std::int64_t vis_single_blocks() const { return n_layer[2]; }
  std::int64_t vis_head_dim() const { return n_embd_dit / n_head_dit; }
  std::int64_t vis_vec_in_dim() const { return pose_emb_dim(); }
  std::int64_t context_in_dim() const { return n_embd; }  // both DiTs read MST features
  std::int64_t traj_double_blocks() const { return n_layer_traj[0]; }
  std::int64_t traj_single_blocks() const { return n_layer_traj[1]; }
  std::int64_t traj_head_dim() const { return n_embd_dit_traj / n_head_dit_traj; }

  // Rough peak of live fp32 activations for one batch-1 step, attention scores materialised
  // (an upper estimate used only to refuse absurd sizes).
  double activation_bytes_estimate() const {
    const double F = double(condition_frames), T = double(tokens_per_frame()), C = double(n_embd);
    const double L = double(img_tokens());
    const double mst = F * T * (4 * C + 4 * C) + F * double(n_head) * T * T + T * double(n_head) * F * F;
    const double S = T + L;  // VisDiT joint sequence: cond tokens then image tokens
    const double D = double(n_embd_dit);
    const double vis = S * (4 * D + 7 * D) + double(n_head_dit) * S * S;
    const double St = T + double(traj_len), Dt = double(n_embd_dit_traj);
    const double traj = St * (4 * Dt + 7 * Dt) + double(n_head_dit_traj) * St * St;
    return 4.0 * std::max({mst, vis, traj});
  }

  // Every value and extent (every problem reported at once); the sizes they add up to are
  // check_size's. Enough to build the layers' skeleton (WorldModel::parameter_list).
  void validate() const {
    detail::ConfigProblems p("WorldModelConfig");
    using detail::max_config_extent;
    auto positive = [&](std::int64_t v, const char* name) {
      p.check(v > 0 && v <= max_config_extent, name, " must be in [1, ", max_config_extent, "], got ", v);
    };
    auto depth = [&](std::int64_t v, std::int64_t least, const char* name) {
      p.check(v >= least && v <= detail::max_config_depth, name, " must be in [", least, ", ",
              detail::max_config_depth, "], got ", v);
    };
    positive(image_h, "image_size[0] (H)");
    positive(image_w, "image_size[1] (W)");
    p.check(downsample_size == constants::dcae_downsample, "downsample_size must be ", constants::dcae_downsample,
            " (the DC-AE f32c32), got ", downsample_size);
    p.check(patch_size == 1, "patch_size must be 1 (the only value the official models use), got ", patch_size);
    positive(vae_embed_dim, "vae_embed_dim");
    p.check(condition_frames >= 1 && condition_frames <= constants::mst_time_emb_rows,
            "condition_frames must be in [1, ", constants::mst_time_emb_rows, "] (rows of the MST time_emb table), got ",
            condition_frames);
    p.check(block_size == 1, "block_size must be 1 for inference, got ", block_size);
    depth(n_layer[0], 1, "n_layer[0] (MST blocks)");
    depth(n_layer[1], 0, "n_layer[1] (VisDiT double blocks)");
    depth(n_layer[2], 0, "n_layer[2] (VisDiT single blocks)");
    depth(n_layer_traj[0], 0, "n_layer_traj[0] (TrajDiT double blocks)");
    depth(n_layer_traj[1], 0, "n_layer_traj[1] (TrajDiT single blocks)");
    p.check(n_layer[1] + n_layer[2] >= 1, "the VisDiT needs at least one block (n_layer[1] + n_layer[2] >= 1)");
    p.check(n_layer_traj[0] + n_layer_traj[1] >= 1, "the TrajDiT needs at least one block (n_layer_traj sum >= 1)");
    positive(traj_len, "traj_len");
    positive(pose_x_vocab_size, "pose_x_vocab_size");
    positive(pose_y_vocab_size, "pose_y_vocab_size");
    positive(yaw_vocab_size, "yaw_vocab_size");
    p.check(std::isfinite(pose_x_bound) && pose_x_bound > 0, "pose_x_bound must be a positive number, got ", pose_x_bound);
    p.check(std::isfinite(pose_y_bound) && pose_y_bound > 0, "pose_y_bound must be a positive number, got ", pose_y_bound);
    p.check(std::isfinite(yaw_bound) && yaw_bound > 0, "yaw_bound must be a positive number, got ", yaw_bound);
    p.check(num_sampling_steps >= 1 && num_sampling_steps <= constants::max_sampling_steps,
            "num_sampling_steps must be in [1, ", constants::max_sampling_steps, "], got ", num_sampling_steps);
    if (image_h > 0 && image_w > 0) {
      p.check(image_h % constants::dcae_downsample == 0 && image_w % constants::dcae_downsample == 0,
              "image_size (", image_h, ", ", image_w, ") must be multiples of ", constants::dcae_downsample);
    }
    check_heads(p, n_embd, n_head, "n_embd", "n_head");
    check_heads(p, n_embd_dit, n_head_dit, "n_embd_dit", "n_head_dit");
    check_heads(p, n_embd_dit_traj, n_head_dit_traj, "n_embd_dit_traj", "n_head_dit_traj");
    if (p.ok()) {
      p.check(mst_head_dim() % 4 == 0, "MST head dim n_embd/n_head = ", mst_head_dim(),
              " must be a multiple of 4 (2-D RoPE rotates head_dim/4 pairs per axis)");
      p.check(n_embd % 2 == 0, "n_embd must be even (img_projector hidden width is n_embd/2), got ", n_embd);
      check_axes(p, axes_dim_dit, vis_head_dim(), "axes_dim_dit", "n_embd_dit/n_head_dit");
      check_axes(p, axes_dim_dit_traj, traj_head_dim(), "axes_dim_dit_traj", "n_embd_dit_traj/n_head_dit_traj");
    }
    p.throw_if_any();
  }

  // The size limits of a valid configuration with `parameters` learnable values, counted from
  // its parameter tree (validate_with_size in model/parameter_counts.hpp, WorldModel::load):
  // parameters, activations and frame size, every problem at once.
  void check_size(double parameters) const {
    detail::check_model_size("WorldModelConfig", "the world model", parameters, 2, "bf16", "one step", activation_bytes_estimate(),
                             image_h, image_w);
  }

 private:
  static void check_heads(detail::ConfigProblems& p, std::int64_t width, std::int64_t heads, const char* wn,
                          const char* hn) {
    p.check(width > 0 && width <= detail::max_config_extent, wn, " must be in [1, ", detail::max_config_extent,
            "], got ", width);
    p.check(heads > 0 && heads <= detail::max_config_extent, hn, " must be in [1, ", detail::max_config_extent,
            "], got ", heads);
    if (width > 0 && heads > 0)
      p.check(width % heads == 0, hn, " (", heads, ") does not divide ", wn, " (", width, ")");
  }
  static void check_axes(detail::ConfigProblems& p, const std::array<std::int64_t, 3>& axes, std::int64_t head_dim,
                         const char* an, const char* hn) {
    std::int64_t sum = 0;
    for (std::size_t i = 0; i < axes.size(); ++i) {
      p.check(axes[i] > 0 && axes[i] % 2 == 0 && axes[i] <= detail::max_config_extent, an, "[", i, "] = ",
              axes[i], " must be positive and even (RoPE rotates pairs)");
      sum += std::min(std::max<std::int64_t>(axes[i], 0), detail::max_config_extent);
    }
    p.check(sum == head_dim, an, " sums to ", sum, " but the head dim ", hn, " is ", head_dim);
  }
};

}  // namespace epona
