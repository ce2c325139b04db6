// epona/model/config/dcae_config.hpp — the DC-AE f32c32 with the temporal decoder front (mirrors
// `models/modules/dcae.py` + the dc-ae config): block, norm and activation kinds, the config, its
// derived sizes and validate(). Its parameter counts come from the parameter tree
// (model/parameter_counts.hpp).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/model/config/constants.hpp"
#include "epona/model/config/problems.hpp"

namespace epona {

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

  // Every value and extent (every problem reported at once); the sizes they add up to are
  // check_size's. Enough to build the layers' skeleton (Dcae::parameter_list).
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
      p.check(temporal_blocks >= 1 && temporal_blocks <= detail::max_config_depth, "temporal n_blocks must be in [1, ",
              detail::max_config_depth, "], got ", temporal_blocks);
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
    p.throw_if_any();
  }

  // The size limits of a valid configuration with `parameters` learnable values, counted from
  // its parameter tree (validate_with_size in model/parameter_counts.hpp, Dcae's constructor):
  // parameters, activations and frame size, every problem at once.
  void check_size(double parameters) const {
    detail::check_model_size("DcaeConfig", "the DC-AE", parameters, 4, "fp32", "one decode", activation_bytes_estimate(),
                             image_h, image_w);
  }

 private:
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
      const bool d_ok = depth[s] >= 0 && depth[s] <= detail::max_config_depth;
      p.check(d_ok, side, " depth_list[", s, "] must be in [0, ", detail::max_config_depth, "], got ", depth[s]);
      p.check(valid(type[s]), side, " block_type[", s, "] is not a known block type");
      p.check(valid(norm[s]), side, " norm[", s, "] is not a known norm");
      p.check(valid(act[s]), side, " act[", s, "] is not a known activation");
      ok = ok && w_ok && d_ok;
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
