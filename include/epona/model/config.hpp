// epona/model/config.hpp — every hyper-parameter of the Epona world model (MST + VisDiT +
// TrajDiT, mirrors the official `configs/dit_config_dcae_*.py`) and of its DC-AE f32c32 with
// the temporal decoder front (mirrors `models/modules/dcae.py` + the dc-ae config), the constants
// the official code hard-codes, derived sizes, exact parameter counts, and validate().
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <string>
#include <string_view>
#include <vector>

#include "epona/core/error.hpp"
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

namespace detail {
// Collects every problem of a config so that validate() reports them all at once.
class ConfigProblems {
 public:
  explicit ConfigProblems(std::string what) : what_(std::move(what)) {}
  template <class... A>
  void check(bool ok, A&&... parts) {
    if (!ok) list_.push_back(concat(std::forward<A>(parts)...));
  }
  bool ok() const { return list_.empty(); }
  void throw_if_any() const {
    if (list_.empty()) return;
    std::string msg = what_ + ": invalid configuration: ";
    for (std::size_t i = 0; i < list_.size(); ++i) msg += (i ? "; " : "") + list_[i];
    fail(msg);
  }

 private:
  std::string what_;
  std::vector<std::string> list_;
};

// Sizes above this are refused before any product is formed (no int64 overflow anywhere).
inline constexpr std::int64_t max_config_extent = std::int64_t{1} << 24;

inline std::string human_bytes(double b) {
  const char* unit[] = {"B", "KB", "MB", "GB", "TB", "PB", "EB"};
  int u = 0;
  while (b >= 1000.0 && u < 6) b /= 1000.0, ++u;
  std::ostringstream os;
  os.precision(3);
  os << b << ' ' << unit[u];
  return os.str();
}
inline std::string human_count(double n) {
  std::ostringstream os;
  os.precision(3);
  os << n;
  return os.str();
}

// The limits every model configuration shares: `params` parameters (stored at `weight_bytes`
// each, `weight_type` named in the message) and `activations` bytes for one `call`.
inline void check_model_size(ConfigProblems& p, const char* model, double params, double weight_bytes,
                             const char* weight_type, const char* call, double activations) {
  p.check(params <= constants::max_parameters, model, " would have ", human_count(params), " parameters (",
          human_bytes(weight_bytes * params), " in ", weight_type, "); the limit is ",
          human_count(constants::max_parameters));
  p.check(activations <= constants::max_activation_bytes, call, " would need about ", human_bytes(activations),
          " of activations; the limit is ", human_bytes(constants::max_activation_bytes));
}

// image_size within constants::max_image_pixels (h, w already checked positive).
inline void check_image_pixels(ConfigProblems& p, std::int64_t h, std::int64_t w) {
  p.check(h <= constants::max_image_pixels / w, "image_size (", h, ", ", w, ") is ", h * w,
          " pixels per frame, more than the limit of ", constants::max_image_pixels, " (16x the released 512x1024)");
}
}  // namespace detail

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

  // ---- exact parameter counts (learnable values of each state_dict) ----
  double mst_parameter_count() const {
    const double C = double(n_embd), P = constants::pose_projector_hidden, E = constants::fourier_embed_dim;
    const double Hi = double(mst_img_projector_hidden());
    const double sub_block = 12 * C * C + 8 * C;  // q,k,v,proj + 4C MLP; ln1, ln2, q_norm, k_norm
    const double img_proj = double(token_dim()) * Hi + Hi * C + 2 * C;
    const double pose_proj = E * P + P * C + 2 * C;
    return double(mst_depth()) * 2 * sub_block + constants::mst_time_emb_rows * C + img_proj + 3 * pose_proj;
  }
  double vis_dit_parameter_count() const {
    const double D = double(n_embd_dit), in = double(token_dim());
    return dit_trunk_parameters(D, double(vis_head_dim()), vis_double_blocks(), vis_single_blocks(), in) +
           mlp_embedder(double(vis_vec_in_dim()), D);  // vector_in
  }
  double traj_dit_parameter_count() const {
    const double D = double(n_embd_dit_traj);
    return dit_trunk_parameters(D, double(traj_head_dim()), traj_double_blocks(), traj_single_blocks(),
                                constants::traj_token_size);
  }
  double parameter_count() const {
    return mst_parameter_count() + vis_dit_parameter_count() + traj_dit_parameter_count();
  }

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

  void validate() const {
    detail::ConfigProblems p("WorldModelConfig");
    using detail::max_config_extent;
    auto positive = [&](std::int64_t v, const char* name) {
      p.check(v > 0 && v <= max_config_extent, name, " must be in [1, ", max_config_extent, "], got ", v);
    };
    auto non_negative = [&](std::int64_t v, const char* name) {
      p.check(v >= 0 && v <= max_config_extent, name, " must be in [0, ", max_config_extent, "], got ", v);
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
    positive(n_layer[0], "n_layer[0] (MST blocks)");
    non_negative(n_layer[1], "n_layer[1] (VisDiT double blocks)");
    non_negative(n_layer[2], "n_layer[2] (VisDiT single blocks)");
    non_negative(n_layer_traj[0], "n_layer_traj[0] (TrajDiT double blocks)");
    non_negative(n_layer_traj[1], "n_layer_traj[1] (TrajDiT single blocks)");
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
    if (p.ok()) {
      detail::check_model_size(p, "the world model", parameter_count(), 2, "bf16", "one step",
                               activation_bytes_estimate());
      detail::check_image_pixels(p, image_h, image_w);
    }
    p.throw_if_any();
  }

 private:
  static double mlp_embedder(double in, double D) { return in * D + D + D * D + D; }
  // img_in/traj_in + time_in + cond_in + blocks + final layer (everything but vector_in).
  double dit_trunk_parameters(double D, double head_dim, std::int64_t n_double, std::int64_t n_single,
                              double in_out) const {
    const double stream = 18 * D * D + 15 * D + 2 * head_dim;  // mod, qkv, qk-norm, proj, mlp
    const double single = 15 * D * D + 11 * D + 2 * head_dim;  // linear1, linear2, qk-norm, modulation
    const double final_layer = in_out * D + in_out + 2 * D * D + 2 * D;
    return (in_out * D + D) + mlp_embedder(constants::timestep_embed_dim, D) + (double(n_embd) * D + D) +
           double(n_double) * 2 * stream + double(n_single) * single + final_layer;
  }
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

// ------------------------------------------------------------------------------------------
// DC-AE f32c32 (mix-1.0 architecture) with Epona's temporal decoder front.
enum class DcaeBlockType : std::uint8_t { ResBlock, EViT_GLU };
enum class DcaeNorm : std::uint8_t { TritonRms2d, BatchNorm2d };  // "trms2d", "bn2d"
enum class DcaeAct : std::uint8_t { ReLU, SiLU };                 // "relu", "silu"

inline std::string_view to_string(DcaeBlockType t) {
  switch (t) {
    case DcaeBlockType::ResBlock: return "ResBlock";
    case DcaeBlockType::EViT_GLU: return "EViT_GLU";
  }
  return "<invalid block type>";
}
inline std::string_view to_string(DcaeNorm n) {
  switch (n) {
    case DcaeNorm::TritonRms2d: return "trms2d";
    case DcaeNorm::BatchNorm2d: return "bn2d";
  }
  return "<invalid norm>";
}
inline std::string_view to_string(DcaeAct a) {
  switch (a) {
    case DcaeAct::ReLU: return "relu";
    case DcaeAct::SiLU: return "silu";
  }
  return "<invalid act>";
}
// Parsers of the official names; unknown names are errors naming the allowed ones.
inline DcaeBlockType dcae_block_type_from(std::string_view s) {
  if (s == "ResBlock") return DcaeBlockType::ResBlock;
  if (s == "EViT_GLU") return DcaeBlockType::EViT_GLU;
  fail("unknown DC-AE block type '", s, "' (supported: ResBlock, EViT_GLU)");
}
inline DcaeNorm dcae_norm_from(std::string_view s) {
  if (s == "trms2d") return DcaeNorm::TritonRms2d;
  if (s == "bn2d") return DcaeNorm::BatchNorm2d;
  fail("unknown DC-AE norm '", s, "' (supported: trms2d, bn2d)");
}
inline DcaeAct dcae_act_from(std::string_view s) {
  if (s == "relu") return DcaeAct::ReLU;
  if (s == "silu") return DcaeAct::SiLU;
  fail("unknown DC-AE activation '", s, "' (supported: relu, silu)");
}

// Default-constructed = Epona's nuPlan DC-AE: f32c32 mix, temporal decoder on, 6-frame clips.
struct DcaeConfig {
  using Ints = std::vector<std::int64_t>;
  std::int64_t in_channels = 3;
  std::int64_t latent_channels = 32;
  Ints encoder_width_list = {128, 256, 512, 512, 1024, 1024};
  Ints encoder_depth_list = {0, 4, 8, 2, 2, 2};
  std::vector<DcaeBlockType> encoder_block_type = {DcaeBlockType::ResBlock, DcaeBlockType::ResBlock,
                                                   DcaeBlockType::ResBlock, DcaeBlockType::EViT_GLU,
                                                   DcaeBlockType::EViT_GLU, DcaeBlockType::EViT_GLU};
  DcaeNorm encoder_norm = DcaeNorm::TritonRms2d;
  DcaeAct encoder_act = DcaeAct::SiLU;
  Ints decoder_width_list = {128, 256, 512, 512, 1024, 1024};
  Ints decoder_depth_list = {0, 5, 10, 2, 2, 2};
  std::vector<DcaeBlockType> decoder_block_type = encoder_block_type;
  std::vector<DcaeNorm> decoder_norm = {DcaeNorm::BatchNorm2d, DcaeNorm::BatchNorm2d, DcaeNorm::BatchNorm2d,
                                        DcaeNorm::TritonRms2d, DcaeNorm::TritonRms2d, DcaeNorm::TritonRms2d};
  std::vector<DcaeAct> decoder_act = {DcaeAct::ReLU, DcaeAct::ReLU, DcaeAct::ReLU,
                                      DcaeAct::SiLU, DcaeAct::SiLU, DcaeAct::SiLU};
  DcaeNorm decoder_out_norm = DcaeNorm::TritonRms2d;
  DcaeAct decoder_out_act = DcaeAct::ReLU;
  // Temporal decoder front (causal_time_block.* / space_block.*): LLaMA-style blocks.
  bool add_decoder_temporal = true;
  std::int64_t condition_frames = 6;  // frames per decoded clip (temporal_patch_size)
  std::int64_t temporal_blocks = 5;   // pairs of (time block, space block)
  std::int64_t temporal_dim = 32;
  std::int64_t temporal_heads = 8;
  std::int64_t temporal_ffn_hidden = 256;
  double temporal_rmsnorm_eps = 1e-5;
  double temporal_rope_theta = 1000.0;
  std::int64_t image_h = 512, image_w = 1024;

  bool operator==(const DcaeConfig&) const = default;

  // ---- derived sizes ----
  std::int64_t latent_h() const { return image_h / constants::dcae_downsample; }
  std::int64_t latent_w() const { return image_w / constants::dcae_downsample; }
  std::int64_t token_size() const { return latent_h() * latent_w(); }
  std::int64_t temporal_head_dim() const { return temporal_dim / temporal_heads; }
  // The official FFN width rule (ModelArgs: hidden = 4*dim -> int(2*hidden/3) -> round up to 256).
  static std::int64_t llama_ffn_hidden(std::int64_t dim, std::int64_t multiple_of = 256) {
    const std::int64_t h = 2 * (4 * dim) / 3;
    return multiple_of * ((h + multiple_of - 1) / multiple_of);
  }

  // ---- exact counts (learnable parameters; BatchNorm running stats + counters separately) ----
  double encoder_parameter_count() const {
    const auto& w = encoder_width_list;
    double n = conv(3, double(in_channels), double(w[1] / 4), true);  // project_in + unshuffle
    for (std::size_t s = 1; s < 6; ++s) {
      n += double(encoder_depth_list[s]) * block_parameters(encoder_block_type[s], double(w[s]), encoder_norm);
      if (s < 5 && encoder_depth_list[s] > 0) n += conv(3, double(w[s]), double(w[s + 1] / 4), true);
    }
    return n + conv(3, double(w[5]), double(latent_channels), true);  // project_out
  }
  double decoder_parameter_count() const {
    const auto& w = decoder_width_list;
    double n = conv(3, double(latent_channels), double(w[5]), true);  // project_in
    for (std::size_t s = 1; s < 6; ++s) {
      if (s < 5 && decoder_depth_list[s] > 0) n += conv(3, double(w[s + 1]), double(4 * w[s]), true);
      n += double(decoder_depth_list[s]) * block_parameters(decoder_block_type[s], double(w[s]), decoder_norm[s]);
    }
    return n + 2 * double(w[1]) + conv(3, double(w[1]), double(4 * in_channels), true);  // out norm + conv
  }
  double temporal_parameter_count() const {
    if (!add_decoder_temporal) return 0;
    const double D = double(temporal_dim), H = double(temporal_ffn_hidden);
    return double(temporal_blocks) * 2 * (4 * D * D + 3 * D * H + 2 * D);
  }
  double parameter_count() const {
    return encoder_parameter_count() + decoder_parameter_count() + temporal_parameter_count();
  }
  // BatchNorm running_mean + running_var + num_batches_tracked elements (stored, not learned).
  double buffer_count() const {
    double n = 0;
    for (std::size_t s = 1; s < 6; ++s) {
      n += double(encoder_depth_list[s]) * block_buffers(encoder_block_type[s], double(encoder_width_list[s]), encoder_norm);
      n += double(decoder_depth_list[s]) *
           block_buffers(decoder_block_type[s], double(decoder_width_list[s]), decoder_norm[s]);
    }
    return n;
  }

  // Rough peak of live fp32 activations of one clip decode (the larger of encode and decode).
  double activation_bytes_estimate() const {
    const double frames = add_decoder_temporal ? double(condition_frames) : 1.0;
    const double pixels = double(image_h) * double(image_w);
    double peak = 6.0 * double(in_channels) * pixels;
    for (std::size_t s = 1; s < 6; ++s) {
      const double at = pixels / std::pow(4.0, double(s));  // stage s runs at (H/2^s, W/2^s)
      for (const auto* w : {&encoder_width_list, &decoder_width_list}) {
        const double c = double((*w)[s]);
        peak = std::max(peak, at * (2 * c + 8 * c + 4 * c));  // input, GLU 8C, gated 4C
      }
    }
    const double L = double(token_size());
    const double temporal = L * L * double(temporal_heads);  // space-attention scores
    return 4.0 * frames * std::max(peak, temporal);
  }

  void validate() const {
    detail::ConfigProblems p("DcaeConfig");
    using detail::max_config_extent;
    auto positive = [&](std::int64_t v, const std::string& name) {
      p.check(v > 0 && v <= max_config_extent, name, " must be in [1, ", max_config_extent, "], got ", v);
    };
    positive(in_channels, "in_channels");
    positive(latent_channels, "latent_channels");
    positive(image_h, "image_size[0] (H)");
    positive(image_w, "image_size[1] (W)");
    if (image_h > 0 && image_w > 0)
      p.check(image_h % constants::dcae_downsample == 0 && image_w % constants::dcae_downsample == 0,
              "image_size (", image_h, ", ", image_w, ") must be multiples of ", constants::dcae_downsample);
    const bool enc_ok = check_stages(p, "encoder", encoder_width_list, encoder_depth_list, encoder_block_type,
                                     std::vector<DcaeNorm>(6, encoder_norm), std::vector<DcaeAct>(6, encoder_act));
    const bool dec_ok = check_stages(p, "decoder", decoder_width_list, decoder_depth_list, decoder_block_type,
                                     decoder_norm, decoder_act);
    p.check(valid(decoder_out_norm), "decoder out_norm is not a known norm");
    p.check(valid(decoder_out_act), "decoder out_act is not a known activation");
    if (enc_ok && latent_channels > 0 && in_channels > 0) {
      const auto& w = encoder_width_list;
      p.check(w[5] % latent_channels == 0, "encoder width_list[5] (", w[5],
              ") must be a multiple of latent_channels (", latent_channels, ") for the averaging shortcut");
      for (std::size_t s = 1; s < 5; ++s)
        p.check(encoder_depth_list[s] > 0, "encoder depth_list[", s,
                "] must be > 0: every stage 1..4 downsamples by 2 (f32 needs all four)");
    }
    if (dec_ok && latent_channels > 0)
      p.check(decoder_width_list[5] % latent_channels == 0, "decoder width_list[5] (", decoder_width_list[5],
              ") must be a multiple of latent_channels (", latent_channels, ") for the duplicating shortcut");
    if (dec_ok)
      for (std::size_t s = 1; s < 5; ++s)
        p.check(decoder_depth_list[s] > 0, "decoder depth_list[", s,
                "] must be > 0: every stage 1..4 upsamples by 2 (f32 needs all four)");
    positive(condition_frames, "condition_frames (temporal clip length)");
    if (add_decoder_temporal) {
      positive(temporal_blocks, "temporal n_blocks");
      positive(temporal_dim, "temporal dim");
      positive(temporal_heads, "temporal n_heads");
      positive(temporal_ffn_hidden, "temporal ffn_hidden");
      p.check(temporal_dim == latent_channels, "temporal dim (", temporal_dim,
              ") must equal latent_channels (", latent_channels, "): the blocks act on the latent");
      if (temporal_dim > 0 && temporal_heads > 0)
        p.check(temporal_dim % temporal_heads == 0 && temporal_head_dim() % 2 == 0, "temporal n_heads (",
                temporal_heads, ") must divide dim (", temporal_dim, ") into an even head dim (RoPE pairs)");
      p.check(std::isfinite(temporal_rmsnorm_eps) && temporal_rmsnorm_eps > 0, "temporal rmsnorm_eps must be > 0");
      p.check(std::isfinite(temporal_rope_theta) && temporal_rope_theta > 0, "temporal rope_theta must be > 0");
    }
    if (p.ok()) {
      detail::check_model_size(p, "the DC-AE", parameter_count(), 4, "fp32", "one decode", activation_bytes_estimate());
      detail::check_image_pixels(p, image_h, image_w);
    }
    p.throw_if_any();
  }

 private:
  static double conv(double k, double in, double out, bool bias) { return out * in * k * k + (bias ? out : 0); }
  static double norm_parameters(double c) { return 2 * c; }  // weight + bias (both norms)
  static double norm_buffers(double c, DcaeNorm n) { return n == DcaeNorm::BatchNorm2d ? 2 * c + 1 : 0; }
  static double block_parameters(DcaeBlockType t, double c, DcaeNorm n) {
    if (t == DcaeBlockType::ResBlock) return conv(3, c, c, true) + conv(3, c, c, false) + norm_parameters(c);
    const double e = constants::dcae_glu_expand * c;
    const double lite_mla = 3 * c * c + c * c + norm_parameters(c);                    // qkv, proj(+norm)
    const double glu = conv(1, c, 2 * e, true) + (2 * e * 9 + 2 * e) + e * c + norm_parameters(c);
    return lite_mla + glu;
  }
  static double block_buffers(DcaeBlockType t, double c, DcaeNorm n) {
    return (t == DcaeBlockType::ResBlock ? 1 : 2) * norm_buffers(c, n);
  }
  static bool valid(DcaeBlockType t) { return t == DcaeBlockType::ResBlock || t == DcaeBlockType::EViT_GLU; }
  static bool valid(DcaeNorm n) { return n == DcaeNorm::TritonRms2d || n == DcaeNorm::BatchNorm2d; }
  static bool valid(DcaeAct a) { return a == DcaeAct::ReLU || a == DcaeAct::SiLU; }

  // Checks one side's per-stage lists; true if they are usable for the size computations.
  static bool check_stages(detail::ConfigProblems& p, const char* side, const Ints& width, const Ints& depth,
                           const std::vector<DcaeBlockType>& type, const std::vector<DcaeNorm>& norm,
                           const std::vector<DcaeAct>& act) {
    const std::size_t n = constants::dcae_stages;
    bool ok = true;
    auto length = [&](std::size_t got, const char* what) {
      p.check(got == n, side, " ", what, " has ", got, " entries, expected ", n);
      ok = ok && got == n;
    };
    length(width.size(), "width_list");
    length(depth.size(), "depth_list");
    length(type.size(), "block_type");
    length(norm.size(), "norm");
    length(act.size(), "act");
    if (!ok) return false;
    for (std::size_t s = 0; s < n; ++s) {
      const bool w_ok = width[s] > 0 && width[s] <= detail::max_config_extent;
      p.check(w_ok, side, " width_list[", s, "] must be in [1, ", detail::max_config_extent, "], got ", width[s]);
      p.check(depth[s] >= 0 && depth[s] <= 1024, side, " depth_list[", s, "] must be in [0, 1024], got ", depth[s]);
      p.check(valid(type[s]), side, " block_type[", s, "] is not a known block type");
      p.check(valid(norm[s]), side, " norm[", s, "] is not a known norm");
      p.check(valid(act[s]), side, " act[", s, "] is not a known activation");
      ok = ok && w_ok && depth[s] >= 0 && depth[s] <= 1024;
      if (w_ok && valid(type[s]) && type[s] == DcaeBlockType::EViT_GLU && depth[s] > 0)
        p.check(width[s] % constants::dcae_litemla_head_dim == 0, side, " width_list[", s, "] (", width[s],
                ") of an EViT_GLU stage must be a multiple of the LiteMLA head dim ",
                constants::dcae_litemla_head_dim);
    }
    p.check(depth[0] == 0, side, " depth_list[0] must be 0 (f32c32: project_in/project_out carry the first 2x "
            "resampling), got ", depth[0]);
    if (!ok) return false;
    for (std::size_t s = 1; s + 1 < n; ++s) {  // 2x pixel (un)shuffle between stage s and s+1
      const bool fits = width[s + 1] % 4 == 0 && (4 * width[s]) % width[s + 1] == 0;
      p.check(fits, side, " width_list[", s, "] = ", width[s], " -> width_list[", s + 1, "] = ", width[s + 1],
              ": the 2x resampling needs width[s+1] % 4 == 0 and 4*width[s] % width[s+1] == 0");
      ok = ok && fits;
    }
    p.check(width[1] % 4 == 0, side, " width_list[1] (", width[1], ") must be a multiple of 4 (pixel shuffle)");
    return ok && width[1] % 4 == 0;
  }
};

}  // namespace epona
