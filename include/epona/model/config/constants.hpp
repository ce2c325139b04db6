// epona/model/config/constants.hpp — the constants the official code hard-codes (not part of any
// config file) and the size limits every configuration is checked against.
#pragma once

#include <cstdint>

#include "epona/flow/sampling_limits.hpp"

namespace epona {

// Constants hard-coded in the official code (not part of any config file).
namespace constants {
// MST (models/stt.py)
inline constexpr double mst_layernorm_eps = 1e-5;  // ln1/ln2/q_norm/k_norm/projector LNs
inline constexpr double mst_rope_theta = 1000.0;   // 2-D axial RoPE of the space attention
inline constexpr int mst_time_emb_rows = 50;       // time_emb table: condition_frames <= 50
inline constexpr int action_tokens = 3;            // per frame: [yaw, pose_x, pose_y]
inline constexpr int pose_tokens = 2;
inline constexpr int yaw_tokens = 1;
// Fourier embedding of the pose/yaw indices (utils/embeddings.py); the projectors' hidden
// width equals it.
inline constexpr int fourier_embed_dim = 512;
inline constexpr double fourier_max_period = 100.0;
inline constexpr int pose_projector_hidden = 512;
// DiT timestep embedding (dit_modules/layers.py)
inline constexpr int timestep_embed_dim = 256;
inline constexpr double timestep_max_period = 10000.0;
inline constexpr double timestep_time_factor = 1000.0;
// FLUX-style DiTs
inline constexpr double dit_rope_theta = 10000.0;
inline constexpr double dit_layernorm_eps = 1e-6;
inline constexpr double dit_rmsnorm_eps = 1e-6;
inline constexpr int dit_mlp_ratio = 4;
inline constexpr int traj_token_size = 3;  // each waypoint is [x, y, yaw]
// The sampling schedule's shift constants: flow/sampling_limits.hpp (the schedule needs them).
// Pose tokenizer ranges (poses_to_indices / yaws_to_indices)
inline constexpr double tokenizer_x_range_m = 8.0;
inline constexpr double tokenizer_y_range_m = 1.0;
inline constexpr double tokenizer_yaw_range_deg = 16.0;
// DC-AE
inline constexpr double dcae_trms2d_eps = 1e-5;
inline constexpr double dcae_batchnorm_eps = 1e-5;
inline constexpr int dcae_litemla_head_dim = 32;
inline constexpr double dcae_litemla_eps = 1e-15;
inline constexpr int dcae_glu_expand = 4;  // GLUMBConv: inverted conv C -> 2*4C, point conv 4C -> C
inline constexpr int dcae_stages = 6;
inline constexpr int dcae_downsample = 32;
// Largest model this library agrees to build (refused with the size it would need).
inline constexpr double max_parameters = 1e11;
inline constexpr double max_activation_bytes = 1e12;
// Frame size of a configuration: 16x the released model's 512x1024 (2048x4096). Between that and
// the terabyte activation limit, a 4096x8192 config was accepted and ran (2.4 GB, 56 s) for a
// model that cannot have been trained at that size. (io/limits.hpp lists every limit.)
inline constexpr std::int64_t max_image_pixels = std::int64_t{16} * 512 * 1024;
// Most rollout frames accepted (the official runs use 54 frames); a larger count is a typo or an
// attack, refused before any output is allocated. (The sampling steps' bound is with the
// schedule, flow/sampling_limits.hpp.)
inline constexpr std::int64_t max_rollout_frames = 1000000;
// Plan hypotheses of one scene (WorldModel::plan_hypotheses): a bound on the batch it runs.
inline constexpr std::int64_t max_hypotheses = 1024;
}  // namespace constants

}  // namespace epona
