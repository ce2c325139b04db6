// epona/model/dcae.hpp — Epona's DC-AE f32c32 (mix-1.0 architecture, `models/modules/dcae.py`):
// the deterministic encoder (image (N, 3, H, W) in [-1, 1] -> latent (N, 32, H/32, W/32)), the
// temporal-aware front (5 x [causal time block, space block] on the latent tokens) and the
// decoder. Sizes, depths, norms and activations come from DcaeConfig; weights bind by official name.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <array>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <utility>
#include <string>
#include <variant>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config/dcae_config.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/nn/conv2d.hpp"
#include "epona/nn/blocks/dcae_blocks.hpp"
#include "epona/nn/feature_map.hpp"
#include "epona/nn/blocks/llama_block.hpp"
#include "epona/nn/norm2d.hpp"
#include "epona/nn/parameter.hpp"
#include "epona/nn/pixel_shuffle.hpp"

namespace epona {

// Where an observer is called (stage = DC-AE stage id 1..5 for the *Stage points, else 0).
enum class DcaePoint {
  EncoderProjectIn,  // after project_in (conv + unshuffle), (1, width[1], H/2, W/2)
  EncoderStage,      // after stage s including its downsample (stage 5 has none)
  EncoderLatent,     // the latent, after project_out
  DecoderTemporal,   // the latent after the temporal blocks (only with add_decoder_temporal)
  DecoderProjectIn,  // after project_in (conv + duplicating shortcut)
  DecoderStage,      // after stage s including its upsample (run from s = 5 down to 1)
  DecoderImage,      // the decoded image, after project_out (no clamp)
};

// Sees every intermediate of one image (1, C, h, w); `image` is its index in the batch.
template <class B>
using DcaeObserver = std::function<void(DcaePoint point, int stage, std::int64_t image, const Tensor<float, B>&)>;

namespace dcae_detail {
inline nn::Norm2dKind norm_kind(DcaeNorm n) {
  return n == DcaeNorm::BatchNorm2d ? nn::Norm2dKind::Batch : nn::Norm2dKind::Rms;
}
inline ConvAct conv_act(DcaeAct a) { return a == DcaeAct::ReLU ? ConvAct::Relu : ConvAct::Silu; }
inline std::string stage_prefix(const std::string& side, std::size_t s) {
  return side + "stages." + std::to_string(s) + ".op_list.";
}

template <class B, class T>
using StageBlock = std::variant<nn::ResBlock<B, T>, nn::EfficientViTBlock<B, T>>;

// `depth` main blocks of one stage, all of one type/norm/act, named op_list.{first + i}.
template <class B, class T>
struct StageBlocks {
  std::vector<StageBlock<B, T>> blocks;
  std::size_t first_index = 0;

  StageBlocks() = default;
  StageBlocks(DcaeBlockType type, std::int64_t width, std::int64_t depth, DcaeNorm norm, DcaeAct act,
              std::size_t first) : first_index(first) {
    for (std::int64_t i = 0; i < depth; ++i) {
      auto n = norm_kind(norm);
      if (type == DcaeBlockType::ResBlock)
        blocks.emplace_back(nn::ResBlock<B, T>(width, n, conv_act(act)));
      else
        blocks.emplace_back(nn::EfficientViTBlock<B, T>(width, n, conv_act(act), constants::dcae_litemla_head_dim,
                                                        static_cast<float>(constants::dcae_litemla_eps),
                                                        constants::dcae_glu_expand));
    }
  }
  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    for (std::size_t i = 0; i < blocks.size(); ++i)
      std::visit([&](auto& b) { b.visit_params(prefix + std::to_string(first_index + i) + ".", v); }, blocks[i]);
  }
  template <class Ctx>
  void forward_inplace(Ctx& ctx, Tensor<activation_t<B, T>, B>& x) const {
    for (const auto& block : blocks) std::visit([&](const auto& b) { b.forward_inplace(ctx, x); }, block);
  }
};

// A pass (encode or decode) recorded as a graph: the staged input/output buffers it reads and
// writes, the key of the sizes last seen, and whether recording failed.
template <class B>
struct PassGraph {
  std::mutex mutex;
  typename BackendTraits<B>::GraphCache graph;
  Tensor<float, B> input, output;
  GraphKey seen;
  bool failed = false;
};

// Shows a map to the observer as public NCHW float32 (converted only where the backend's maps differ).
template <class Ctx, class A, class B>
void notify(Ctx& ctx, const DcaeObserver<B>& obs, DcaePoint p, int stage, std::int64_t image, const Tensor<A, B>& t) {
  if (!obs) return;
  if constexpr (!channels_last_maps<B> && std::is_same_v<A, float>)
    obs(p, stage, image, t);
  else
    obs(p, stage, image, nn::map_to_nchw(ctx, t));
}
}  // namespace dcae_detail

// DC-AE encoder: project_in (conv 3 -> width[1]/4 + unshuffle), stages 1..5 (blocks, then a
// downsample pair for s < 5), project_out (conv width[5] -> latent + channel-averaging shortcut).
template <class B, class T>
struct DcaeEncoder : nn::Bindable<DcaeEncoder<B, T>> {
  nn::DownsampleBlock<B, T> project_in;
  std::vector<dcae_detail::StageBlocks<B, T>> stages;      // index s = stage id (0 is empty)
  std::vector<nn::DownsampleBlock<B, T>> downsample;        // index s, for s < 5 with depth > 0
  nn::Conv2d<B, T> project_out;
  std::int64_t latent_channels = 0;

  DcaeEncoder() = default;
  explicit DcaeEncoder(const DcaeConfig& c)
      : project_in(c.in_channels, c.encoder_width_list[1], false),
        project_out(c.encoder_width_list[5], c.latent_channels, 3),
        latent_channels(c.latent_channels) {
    const auto& w = c.encoder_width_list;
    for (std::size_t s = 0; s < w.size(); ++s) {
      const std::int64_t depth = c.encoder_depth_list[s];
      stages.emplace_back(c.encoder_block_type[s], w[s], depth, c.encoder_norm, c.encoder_act, 0);
      const bool down = s + 1 < w.size() && depth > 0;
      downsample.emplace_back(down ? nn::DownsampleBlock<B, T>(w[s], w[s + 1], true) : nn::DownsampleBlock<B, T>());
    }
  }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    project_in.visit_params(prefix + "project_in.", v);
    for (std::size_t s = 0; s < stages.size(); ++s) {
      const std::string p = dcae_detail::stage_prefix(prefix, s);
      stages[s].visit_params(p, v);
      if (has_downsample(s)) downsample[s].visit_params(p + std::to_string(stages[s].blocks.size()) + ".", v);
    }
    project_out.visit_params(prefix + "project_out.main.op_list.0.conv.", v);
  }

  using Map = Tensor<activation_t<B, T>, B>;

  // image map (1 image, `in` channels, H x W) -> latent map (latent channels, H/32 x W/32), in B's layout
  template <class Ctx>
  Map forward(Ctx& ctx, const Map& image, std::int64_t index, const DcaeObserver<B>& obs) const {
    using dcae_detail::notify;
    Map x = project_in.forward(ctx, image);
    notify(ctx, obs, DcaePoint::EncoderProjectIn, 0, index, x);
    for (std::size_t s = 1; s < stages.size(); ++s) {
      stages[s].forward_inplace(ctx, x);
      if (has_downsample(s)) x = downsample[s].forward(ctx, x);
      notify(ctx, obs, DcaePoint::EncoderStage, static_cast<int>(s), index, x);
    }
    Map z = project_out.forward(ctx, x);
    nn::add_channel_average_down(ctx, x, z, 1);
    notify(ctx, obs, DcaePoint::EncoderLatent, 0, index, z);
    return z;
  }

 private:
  bool has_downsample(std::size_t s) const { return downsample[s].conv.out_channels > 0; }
};

// DC-AE decoder: project_in (conv latent -> width[5] + duplicating shortcut), stages 5..1 (an
// upsample pair as op_list.0 for s < 5, then the blocks), project_out (norm, act, conv width[1]
// -> 4·in + shuffle; no clamp).
template <class B, class T>
struct DcaeDecoder : nn::Bindable<DcaeDecoder<B, T>> {
  nn::Conv2d<B, T> project_in;
  std::vector<nn::UpsampleBlock<B, T>> upsample;            // index s, for s < 5 with depth > 0
  std::vector<dcae_detail::StageBlocks<B, T>> stages;       // index s = stage id (0 is empty)
  nn::Norm2d<B, T> out_norm;
  ConvAct out_act = ConvAct::Relu;
  nn::UpsampleBlock<B, T> project_out;

  DcaeDecoder() = default;
  explicit DcaeDecoder(const DcaeConfig& c)
      : project_in(c.latent_channels, c.decoder_width_list[5], 3),
        out_norm(dcae_detail::norm_kind(c.decoder_out_norm), c.decoder_width_list[1]),
        out_act(dcae_detail::conv_act(c.decoder_out_act)),
        project_out(c.decoder_width_list[1], c.in_channels, false) {
    const auto& w = c.decoder_width_list;
    for (std::size_t s = 0; s < w.size(); ++s) {
      const std::int64_t depth = c.decoder_depth_list[s];
      const bool up = s + 1 < w.size() && depth > 0;
      upsample.emplace_back(up ? nn::UpsampleBlock<B, T>(w[s + 1], w[s], true) : nn::UpsampleBlock<B, T>());
      stages.emplace_back(c.decoder_block_type[s], w[s], depth, c.decoder_norm[s], c.decoder_act[s], up ? 1 : 0);
    }
  }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    project_in.visit_params(prefix + "project_in.main.conv.", v);
    for (std::size_t s = 0; s < stages.size(); ++s) {
      const std::string p = dcae_detail::stage_prefix(prefix, s);
      if (has_upsample(s)) upsample[s].visit_params(p + "0.", v);
      stages[s].visit_params(p, v);
    }
    out_norm.visit_params(prefix + "project_out.op_list.0.", v);
    project_out.visit_params(prefix + "project_out.op_list.2.", v);  // op_list.1 is the activation
  }

  using Map = Tensor<activation_t<B, T>, B>;

  // latent map (1 image, latent channels, h x w) -> image map (`in` channels, 32h x 32w), in B's layout
  template <class Ctx>
  Map forward(Ctx& ctx, const Map& z, std::int64_t index, const DcaeObserver<B>& obs) const {
    Map image = project_out.forward(ctx, features(ctx, z, index, obs));
    dcae_detail::notify(ctx, obs, DcaePoint::DecoderImage, 0, index, image);
    return image;
  }

  // The same, written as the public NCHW float32 image (1, in, 32h, 32w) into `image`: the last
  // pixel shuffle and the layout change are one pass where the backend fuses them.
  template <class Ctx>
  void forward_into(Ctx& ctx, const Map& z, std::int64_t index, const DcaeObserver<B>& obs,
                    Tensor<float, B>& image) const {
    EPONA_CHECK(!project_out.shortcut, "DcaeDecoder: project_out has no shortcut");
    nn::pixel_shuffle_to_nchw(ctx, project_out.conv.forward(ctx, features(ctx, z, index, obs)),
                              nn::UpsampleBlock<B, T>::factor, image);
    if (obs) obs(DcaePoint::DecoderImage, 0, index, image);
  }

 private:
  bool has_upsample(std::size_t s) const { return upsample[s].conv.out_channels > 0; }

  // project_in, the stages and project_out's norm + act: the map project_out's conv reads.
  template <class Ctx>
  Map features(Ctx& ctx, const Map& z, std::int64_t index, const DcaeObserver<B>& obs) const {
    using dcae_detail::notify;
    Map x = project_in.forward(ctx, z);
    nn::add_channel_duplicate_up(ctx, z, x, 1);
    notify(ctx, obs, DcaePoint::DecoderProjectIn, 0, index, x);
    for (std::size_t s = stages.size(); s-- > 1;) {
      if (has_upsample(s)) x = upsample[s].forward(ctx, x);
      stages[s].forward_inplace(ctx, x);
      notify(ctx, obs, DcaePoint::DecoderStage, static_cast<int>(s), index, x);
    }
    out_norm.forward_inplace(ctx, x, out_act);
    return x;
  }
};

// Epona's temporal-aware front: for i = 0..n-1, `causal_time_block.{i}` over the frames of each
// clip (per latent token, causal, RoPE position = frame), then `space_block.{i}` over the tokens
// of each frame (full, RoPE position = y·w + x).
template <class B, class T>
struct DcaeTemporalBlocks : nn::Bindable<DcaeTemporalBlocks<B, T>> {
  std::vector<nn::TransformerBlock<B, T>> time_blocks, space_blocks;

  DcaeTemporalBlocks() = default;
  explicit DcaeTemporalBlocks(const DcaeConfig& c) {
    const nn::TransformerBlock<B, T> block(c.temporal_dim, c.temporal_heads, c.temporal_ffn_hidden,
                                           static_cast<float>(c.temporal_rmsnorm_eps),
                                           static_cast<float>(c.temporal_rope_theta));
    time_blocks.assign(static_cast<std::size_t>(c.temporal_blocks), block);
    space_blocks.assign(static_cast<std::size_t>(c.temporal_blocks), block);
  }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    for (std::size_t i = 0; i < time_blocks.size(); ++i) {
      time_blocks[i].visit_params(prefix + "causal_time_block." + std::to_string(i) + ".", v);
      space_blocks[i].visit_params(prefix + "space_block." + std::to_string(i) + ".", v);
    }
  }

  using Map = Tensor<activation_t<B, T>, B>;

  // latent map (N = clips · frames latents, clip-major) -> same extents, in B's layout.
  template <class Ctx>
  Map forward(Ctx& ctx, const Map& latent, std::int64_t frames) const {
    const nn::MapDims d = nn::map_dims(latent, "temporal blocks");
    const std::int64_t N = d.batch, L = d.pixels(), C = d.channels;
    EPONA_CHECK(frames > 0 && N % frames == 0, "temporal blocks: ", N, " latents are not whole clips of ", frames,
                " frames");
    const std::int64_t clips = N / frames;
    Tensor<float, B> x = to_tokens(ctx, latent).reshape({N * L, C});  // rows (clip, f, l), float32
    const nn::TokenSequences time{clips, L, frames, 1, L, true}, space{clips, frames, L, L, 1, false};
    if (!time_blocks.empty()) {
      const auto& time_rope = rope_tables(time);
      const auto& space_rope = rope_tables(space);
      if (!forward_fused(ctx, x, time, space, time_rope, space_rope))
        for (std::size_t i = 0; i < time_blocks.size(); ++i) {
          time_blocks[i].forward_inplace(ctx, x, time, time_rope.first.data(), time_rope.second.data());
          space_blocks[i].forward_inplace(ctx, x, space, space_rope.first.data(), space_rope.second.data());
        }
    }
    return from_tokens(ctx, x.reshape({N, L, C}), d);
  }

  // Makes the RoPE tables a forward over N latents of h x w in clips of `frames` will use, so that
  // the forward itself only launches work (it may then be recorded as a CUDA graph).
  void prepare(std::int64_t N, std::int64_t h, std::int64_t w, std::int64_t frames) const {
    if (time_blocks.empty() || frames <= 0 || N % frames != 0) return;
    const std::int64_t L = h * w, clips = N / frames;
    rope_tables({clips, L, frames, 1, L, true});
    rope_tables({clips, frames, L, L, 1, false});
  }

 private:
  using Tables = std::pair<Tensor<float, B>, Tensor<float, B>>;
  struct RopeCache {
    std::mutex mutex;
    std::map<std::array<std::int64_t, 6>, Tables> tables;
  };

  // One block of the chain handed to a backend's fused_transformer_blocks.
  struct FusedStep {
    const nn::TransformerBlock<B, T>* block;
    nn::TokenSequences seq;
    const float *cos, *sin;
  };

  // The whole chain T0 S0 T1 S1 … as one fused call where the backend has one (CUDA:
  // cuda/conv/dcae_temporal.cuh); false when it has none or declines (then the blocks run one by one).
  template <class Ctx>
  bool forward_fused(Ctx& ctx, Tensor<float, B>& x, const nn::TokenSequences& time, const nn::TokenSequences& space,
                     const Tables& time_rope, const Tables& space_rope) const {
    if constexpr (is_host_backend<B>) {
      return false;
    } else {
      std::vector<FusedStep> steps;
      for (std::size_t i = 0; i < time_blocks.size(); ++i) {
        steps.push_back({&time_blocks[i], time, time_rope.first.data(), time_rope.second.data()});
        steps.push_back({&space_blocks[i], space, space_rope.first.data(), space_rope.second.data()});
      }
      return fused_transformer_blocks(ctx, x.data(), x.size(0), steps);
    }
  }

  // (cos, sin) of rope_table_1d in B's memory, made once per sequence layout and kept.
  const Tables& rope_tables(const nn::TokenSequences& seq) const {
    const auto& b = time_blocks.front();
    const std::array<std::int64_t, 6> key{seq.groups, seq.seqs, seq.length, seq.seq_step, seq.pos_step, b.head_dim()};
    std::lock_guard<std::mutex> lock(rope_cache_->mutex);
    auto it = rope_cache_->tables.find(key);
    if (it == rope_cache_->tables.end()) {
      std::vector<float> c, s;
      nn::rope_table_1d(seq, b.head_dim(), b.rope_theta, c, s);
      const Shape shape{seq.rows(), b.head_dim() / 2};
      const auto place = [&](std::vector<float>& v) {
        return BackendTraits<B>::upload(Tensor<float, Cpu>::view(v.data(), shape).clone());
      };
      it = rope_cache_->tables.emplace(key, Tables{place(c), place(s)}).first;
    }
    return it->second;
  }
  std::shared_ptr<RopeCache> rope_cache_ = std::make_shared<RopeCache>();

  // A latent map as float32 (N, L, C) tokens (a new tensor) and back: a copy (with the type
  // conversion) channels-last, a transpose in NCHW.
  template <class Ctx>
  static Tensor<float, B> to_tokens(Ctx& ctx, const Map& latent) {
    if constexpr (channels_last_maps<B>) return nn::converted<float>(ctx, latent);
    else return latent_to_tokens(ctx, latent);
  }
  template <class Ctx>
  static Map from_tokens(Ctx& ctx, const Tensor<float, B>& tokens, const nn::MapDims& d) {
    if constexpr (channels_last_maps<B>) return nn::converted<activation_t<B, T>>(ctx, tokens).reshape(nn::map_shape<B>(d));
    else return tokens_to_latent(ctx, tokens, d.height, d.width);
  }
};

// FLOPs of one pass at H x W, counted as torch.utils.flop_counter counts them: 2 per
// multiply-accumulate of every convolution and matrix product (LiteMLA's padded [v; 1] products
// and the temporal blocks' projections and attention included); biases, norms, activations,
// softmax, residual adds and shortcuts excluded.
struct DcaeFlops {
  double encode = 0;           // one image
  double decode = 0;           // one image, convolutional decoder only
  double temporal = 0;         // temporal blocks for one image decoded in a clip of `frames`
  double decode_total() const { return decode + temporal; }
};

inline DcaeFlops dcae_flops(const DcaeConfig& c, std::int64_t height, std::int64_t width, std::int64_t frames = 1) {
  const double d = constants::dcae_litemla_head_dim, e = constants::dcae_glu_expand;
  const auto pixels = [&](std::size_t s) { return double(height) * double(width) / std::pow(4.0, double(s)); };
  const auto conv = [](double k, double in, double out, double p) { return k * k * in * out * p; };
  const auto block = [&](DcaeBlockType t, double C, double P) {
    if (t == DcaeBlockType::ResBlock) return 2 * conv(3, C, C, P);
    const double n = P, heads = C / d;
    const double attention = heads * (n > d ? 2 * (d + 1) * d * n : 2 * d * n * n);
    return conv(1, C, 3 * C, P) + attention + conv(1, C, C, P) + conv(1, C, 2 * e * C, P) + 9 * 2 * e * C * P +
           conv(1, e * C, C, P);
  };
  DcaeFlops f;
  const auto& we = c.encoder_width_list;
  double enc = conv(3, double(c.in_channels), double(we[1] / 4), pixels(0));
  for (std::size_t s = 1; s < we.size(); ++s) {
    enc += double(c.encoder_depth_list[s]) * block(c.encoder_block_type[s], double(we[s]), pixels(s));
    if (s + 1 < we.size() && c.encoder_depth_list[s] > 0) enc += conv(3, double(we[s]), double(we[s + 1] / 4), pixels(s));
  }
  enc += conv(3, double(we.back()), double(c.latent_channels), pixels(we.size() - 1));
  const auto& wd = c.decoder_width_list;
  const std::size_t last = wd.size() - 1;
  double dec = conv(3, double(c.latent_channels), double(wd[last]), pixels(last));
  for (std::size_t s = 1; s < wd.size(); ++s) {
    if (s < last && c.decoder_depth_list[s] > 0) dec += conv(3, double(wd[s + 1]), double(4 * wd[s]), pixels(s + 1));
    dec += double(c.decoder_depth_list[s]) * block(c.decoder_block_type[s], double(wd[s]), pixels(s));
  }
  dec += conv(3, double(wd[1]), double(4 * c.in_channels), pixels(1));
  if (c.add_decoder_temporal) {
    const double L = pixels(last), D = double(c.temporal_dim), F = double(frames);
    const double linears = 4 * D * D * L + 3 * D * double(c.temporal_ffn_hidden) * L;  // per block, per frame
    const double attention = 2 * D * (F * L + L * L);  // time: L sequences of F per clip / F; space: L x L
    f.temporal = 2 * double(c.temporal_blocks) * (2 * linears + attention);
  }
  f.encode = 2 * enc;
  f.decode = 2 * dec;
  return f;
}

// The whole autoencoder. encode: (N, 3, H, W) in [-1, 1] -> (N, 32, H/32, W/32); decode: the
// inverse, with the temporal front over single frames (is_video = false) or over clips of
// condition_frames consecutive latents (is_video = true, N a multiple of it). H and W may be any
// multiples of 32 (the reference's RoPE tables fix them to the config's image size).
// Images are processed one at a time through the convolutional parts (bounded memory).
template <class B, class T>
class Dcae : public nn::Bindable<Dcae<B, T>> {
 public:
  using Act = activation_t<B, T>;  // feature maps inside (float on the CPU; T on CUDA)
  using Map = Tensor<Act, B>;

  // The layers, sized from `config` (validated, its sizes included); no weights until bound or
  // randomised.
  explicit Dcae(DcaeConfig config) : Dcae(std::move(config), Skeleton{}) {
    config_.check_size(this->parameters().learned_count());
  }

  // The parameter tree of a configuration without weights (names, shapes; counts by prefix
  // "encoder.", "decoder.", "causal_time_block.", "space_block."): the layers' skeleton visited
  // with nn::ParamList. `config` is validated, but for its sizes (DcaeConfig::check_size).
  static nn::ParamList parameter_list(const DcaeConfig& config) { return Dcae(config, Skeleton{}).parameters(); }

  // Binds every parameter from `weights` (official names, no prefix); throws one error naming
  // every missing / mis-shaped key, and with `strict` every unexpected one. BatchNorm's
  // `num_batches_tracked` counters are accepted and ignored.
  static Dcae load(const io::TensorMap& weights, const DcaeConfig& config, bool strict = true) {
    Dcae model(config);
    io::BindReport report(weights);
    nn::ParamBinder binder(report);
    model.visit_params("", binder);
    report.finish(strict, [&](const std::string& name) { return binder.is_counter(name); });
    return model;
  }

  const DcaeConfig& config() const { return config_; }

  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    encoder.visit_params(prefix + "encoder.", v);
    decoder.visit_params(prefix + "decoder.", v);
    temporal.visit_params(prefix, v);
  }

  // images (N, in, H, W) float32 NCHW in [-1, 1] -> latents (N, latent, H/32, W/32) float32 NCHW.
  template <class Ctx>
  Tensor<float, B> encode(Ctx& ctx, const Tensor<float, B>& images, const DcaeObserver<B>& obs = {}) const {
    EPONA_CHECK(images.dim() == 4 && images.size(1) == config_.in_channels, "Dcae::encode: images must be (N, ",
                config_.in_channels, ", H, W), got ", shape_str(images.shape()));
    check_multiple(images.size(2), images.size(3), "Dcae::encode: image");
    const std::int64_t f = constants::dcae_downsample;
    const Shape out{images.size(0), config_.latent_channels, images.size(2) / f, images.size(3) / f};
    const auto work = [&](const Tensor<float, B>& in, Tensor<float, B>& latents) { encode_into(ctx, in, latents, obs); };
    return run_pass(ctx, *encode_graph_, images, out, 0, !obs, work);
  }

  // latents (N, latent, h, w) float32 NCHW -> images (N, in, 32h, 32w) float32 NCHW (not clamped).
  template <class Ctx>
  Tensor<float, B> decode(Ctx& ctx, const Tensor<float, B>& latents, bool is_video,
                          const DcaeObserver<B>& obs = {}) const {
    EPONA_CHECK(latents.dim() == 4 && latents.size(1) == config_.latent_channels, "Dcae::decode: latents must be (N, ",
                config_.latent_channels, ", h, w), got ", shape_str(latents.shape()));
    const std::int64_t N = latents.size(0), f = constants::dcae_downsample;
    const std::int64_t frames = is_video ? config_.condition_frames : 1;
    EPONA_CHECK(N % frames == 0, "Dcae::decode(is_video): ", N, " latents are not whole clips of condition_frames = ",
                frames);
    if (config_.add_decoder_temporal) temporal.prepare(N, latents.size(2), latents.size(3), frames);
    const Shape out{N, config_.in_channels, latents.size(2) * f, latents.size(3) * f};
    const auto work = [&](const Tensor<float, B>& in, Tensor<float, B>& images) {
      decode_into(ctx, in, frames, images, obs);
    };
    return run_pass(ctx, *decode_graph_, latents, out, static_cast<std::uint64_t>(frames), !obs, work);
  }

  // Backends with graphs (CUDA): from the second call with the same sizes on, encode/decode
  // without an observer replay the pass recorded as one CUDA graph (the inputs are copied into
  // a buffer the graph reads; results are copied out of the one it writes). Off: always eager.
  bool use_graphs = true;

  DcaeEncoder<B, T> encoder;
  DcaeDecoder<B, T> decoder;
  DcaeTemporalBlocks<B, T> temporal;  // empty without add_decoder_temporal

 private:
  struct Skeleton {};
  Dcae(DcaeConfig config, Skeleton) : config_((config.validate(), std::move(config))) {
    encoder = DcaeEncoder<B, T>(config_);
    decoder = DcaeDecoder<B, T>(config_);
    if (config_.add_decoder_temporal) temporal = DcaeTemporalBlocks<B, T>(config_);
  }

  static void check_multiple(std::int64_t h, std::int64_t w, const char* what) {
    const std::int64_t f = constants::dcae_downsample;
    EPONA_CHECK(h > 0 && w > 0 && h % f == 0 && w % f == 0, what, " size ", h, "x", w, " is not a multiple of ", f);
  }

  template <class Ctx>
  void encode_into(Ctx& ctx, const Tensor<float, B>& images, Tensor<float, B>& latents, const DcaeObserver<B>& obs) const {
    for (std::int64_t n = 0; n < images.size(0); ++n) {
      const Map image = nn::map_from_nchw<Act>(ctx, images.slice(n, n + 1));
      Tensor<float, B> out = latents.slice(n, n + 1);
      nn::map_to_nchw(ctx, encoder.forward(ctx, image, n, obs), out);
    }
  }

  template <class Ctx>
  void decode_into(Ctx& ctx, const Tensor<float, B>& latents, std::int64_t frames, Tensor<float, B>& images,
                   const DcaeObserver<B>& obs) const {
    Map z = nn::map_from_nchw<Act>(ctx, latents);
    if (config_.add_decoder_temporal) {
      z = temporal.forward(ctx, z, frames);
      for (std::int64_t n = 0; n < z.size(0); ++n)
        dcae_detail::notify(ctx, obs, DcaePoint::DecoderTemporal, 0, n, z.slice(n, n + 1));
    }
    for (std::int64_t n = 0; n < latents.size(0); ++n) {
      Tensor<float, B> out = images.slice(n, n + 1);
      decoder.forward_into(ctx, z.slice(n, n + 1), n, obs, out);
    }
  }

  // One pass into a new result of `out_shape`: eager, or (graph-capable backends, `replayable`)
  // through the staged buffers and the recorded graph of `g`. The first call with given sizes
  // runs eagerly (it makes cuDNN/cuBLASLt plans and tables outside any recording); the next
  // records; later ones replay. A pass that cannot be recorded stays eager from then on.
  template <class Ctx, class Work>
  Tensor<float, B> run_pass(Ctx& ctx, dcae_detail::PassGraph<B>& g, const Tensor<float, B>& in, const Shape& out_shape,
                            std::uint64_t variant, bool replayable, const Work& work) const {
    Tensor<float, B> result = nn::new_result<float, B>(ctx, out_shape);
    if constexpr (!is_host_backend<B>) {
      if (replayable && use_graphs) {
        std::lock_guard<std::mutex> lock(g.mutex);
        if (!g.failed) {
          if (g.input.shape() != in.shape()) g.input = Tensor<float, B>(in.shape());
          if (g.output.shape() != out_shape) g.output = Tensor<float, B>(out_shape);
          copy(ctx, g.input, in);
          GraphKey key{reinterpret_cast<std::uint64_t>(g.input.data()), reinterpret_cast<std::uint64_t>(g.output.data()),
                       variant, graph_variant(ctx)};
          for (const auto d : in.shape()) key.push_back(static_cast<std::uint64_t>(d));
          if (key != g.seen) {
            work(g.input, g.output);  // eager first run with these sizes
            g.seen = key;
          } else {
            try {
              g.graph.run(ctx, key, [&] { work(g.input, g.output); });
            } catch (const Error&) {
              g.failed = true;  // not recordable here: run eagerly from now on
              work(g.input, g.output);
            }
          }
          copy(ctx, result, g.output);
          return result;
        }
      }
    }
    work(in, result);
    return result;
  }

  std::shared_ptr<dcae_detail::PassGraph<B>> encode_graph_ = std::make_shared<dcae_detail::PassGraph<B>>();
  std::shared_ptr<dcae_detail::PassGraph<B>> decode_graph_ = std::make_shared<dcae_detail::PassGraph<B>>();
  DcaeConfig config_;
};

}  // namespace epona
