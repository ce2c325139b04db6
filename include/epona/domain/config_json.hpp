// epona/domain/config_json.hpp — reads and writes the model configuration as JSON: the golden
// `configs.json` layout (`world_model_config` + `dcae.{config, image_size, temporal_block}`,
// the official config dict with the dc-ae config) or a plain object holding only the
// world-model keys. Every key used must be present with the right type; errors name the key.
#pragma once

#include <algorithm>
#include <filesystem>
#include <initializer_list>
#include <fstream>
#include <sstream>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "epona/core/error.hpp"
#include "epona/core/printable.hpp"
#include "epona/io/json_reader.hpp"
#include "epona/model/config.hpp"
#include "epona/model/parameter_counts.hpp"
#include "epona/model/plan_choice.hpp"

namespace epona::io {

// Both configurations that come with a set of weights.
struct ModelConfigs {
  WorldModelConfig world;
  DcaeConfig dcae;
  model::PlanningRule planner;  // optional "planner" block: the model's recommended planning rule
  bool operator==(const ModelConfigs&) const = default;
};

namespace config_detail {
using nlohmann::json;

// A JSON object plus where it sits ("configs.json: dcae.config.encoder"), for error messages.
class JsonObject {
 public:
  JsonObject(const json& j, std::string source, std::string path)
      : j_(j), source_(std::move(source)), path_(std::move(path)) {
    EPONA_CHECK(j_.is_object(), where(), " must be a JSON object, got ", type_of(j_));
  }

  bool has(const char* key) const { return j_.contains(key); }
  JsonObject object(const char* key) const { return JsonObject(at(key), source_, name(key)); }

  std::int64_t integer(const char* key) const { return to_integer(at(key), key); }
  double number(const char* key) const {
    const json& v = at(key);
    EPONA_CHECK(v.is_number(), bad_type(key, "a number", v));
    return v.get<double>();
  }
  bool boolean(const char* key) const {
    const json& v = at(key);
    EPONA_CHECK(v.is_boolean(), bad_type(key, "true or false", v));
    return v.get<bool>();
  }
  std::string string(const char* key) const {
    const json& v = at(key);
    EPONA_CHECK(v.is_string(), bad_type(key, "a string", v));
    return v.get<std::string>();
  }
  std::vector<std::int64_t> integers(const char* key) const {
    const json& v = array(key);
    std::vector<std::int64_t> out;
    for (std::size_t i = 0; i < v.size(); ++i) out.push_back(to_integer(v[i], key, static_cast<std::ptrdiff_t>(i)));
    return out;
  }
  template <std::size_t N>
  std::array<std::int64_t, N> integers_n(const char* key) const {
    const auto v = integers(key);
    EPONA_CHECK(v.size() == N, where(key), " must have ", N, " entries, got ", v.size());
    std::array<std::int64_t, N> out{};
    std::copy(v.begin(), v.end(), out.begin());
    return out;
  }
  // A list of strings; a single string is accepted and repeated `broadcast` times (when > 0).
  std::vector<std::string> strings(const char* key, std::size_t broadcast = 0) const {
    const json& v = at(key);
    if (v.is_string() && broadcast > 0) return std::vector<std::string>(broadcast, v.get<std::string>());
    EPONA_CHECK(v.is_array(), bad_type(key, broadcast ? "a string or a list of strings" : "a list of strings", v));
    std::vector<std::string> out;
    for (std::size_t i = 0; i < v.size(); ++i) {
      EPONA_CHECK(v[i].is_string(), where(key), "[", i, "] must be a string, got ", type_of(v[i]));
      out.push_back(v[i].get<std::string>());
    }
    return out;
  }
  // Keys that describe architecture choices this library implements in one way only.
  void expect(const char* key, const json& supported) const {
    const json& v = at(key);
    EPONA_CHECK(v == supported, where(key), " = ", json_brief(v), " is not supported (only ", supported.dump(), ")");
  }
  // Converts a name with `parse` (which throws for unknown names), adding the key to the error.
  template <class Parse>
  auto parsed(const char* key, const std::string& value, Parse parse) const {
    try {
      return parse(value);
    } catch (const Error& e) {
      fail(where(key), ": ", e.what());
    }
  }
  // Refuses any key outside `known` (a misspelt optional key would otherwise be ignored silently).
  void only_keys(std::initializer_list<std::string_view> known) const {
    for (auto it = j_.begin(); it != j_.end(); ++it)
      EPONA_CHECK(std::find(known.begin(), known.end(), std::string_view(it.key())) != known.end(), where(),
                  ": unknown key ", json_brief(json(it.key())));
  }
  std::string where(const char* key = nullptr) const {
    return source_ + ": " + (key ? name(key) : (path_.empty() ? std::string("top level") : path_));
  }

 private:
  const json& at(const char* key) const {
    auto it = j_.find(key);
    EPONA_CHECK(it != j_.end(), source_, ": missing key '", name(key), "'");
    return *it;
  }
  const json& array(const char* key) const {
    const json& v = at(key);
    EPONA_CHECK(v.is_array(), bad_type(key, "a list", v));
    return v;
  }
  std::string name(const char* key) const { return path_.empty() ? key : path_ + "." + key; }
  // Never v.dump(): it walks the value (a 300k-deep list overflowed the stack) and echoes it whole.
  static std::string type_of(const json& v) { return std::string(v.type_name()) + " " + json_brief(v); }
  std::string bad_type(const char* key, const char* expected, const json& v) const {
    return where(key) + " must be " + expected + ", got " + type_of(v);
  }
  // Integers may be written 50 or 50.0; anything fractional or out of int64 range is an error.
  std::int64_t to_integer(const json& v, const char* key, std::ptrdiff_t index = -1) const {
    const std::string at_ = index < 0 ? where(key) : where(key) + "[" + std::to_string(index) + "]";
    if (v.is_number_unsigned()) {  // first: is_number_integer() is true for unsigned values too
      EPONA_CHECK(v.get<std::uint64_t>() <= std::uint64_t(INT64_MAX), at_, " is out of range: ", json_brief(v));
      return static_cast<std::int64_t>(v.get<std::uint64_t>());
    }
    if (v.is_number_integer()) return v.get<std::int64_t>();
    EPONA_CHECK(v.is_number_float(), at_, " must be an integer, got ", type_of(v));
    const double d = v.get<double>();
    EPONA_CHECK(std::isfinite(d) && d == std::floor(d) && std::fabs(d) < 9.2e18, at_,
                " must be an integer, got ", json_brief(v));
    return static_cast<std::int64_t>(d);
  }

  const json& j_;
  std::string source_, path_;
};

inline std::array<std::int64_t, 2> image_size(const JsonObject& o) { return o.integers_n<2>("image_size"); }

inline std::vector<DcaeBlockType> block_types(const JsonObject& o) {
  std::vector<DcaeBlockType> out;
  for (const auto& s : o.strings("block_type")) out.push_back(o.parsed("block_type", s, dcae_block_type_from));
  return out;
}
inline std::vector<DcaeNorm> norms(const JsonObject& o, const char* key, std::size_t stages) {
  std::vector<DcaeNorm> out;
  for (const auto& s : o.strings(key, stages)) out.push_back(o.parsed(key, s, dcae_norm_from));
  return out;
}
inline std::vector<DcaeAct> acts(const JsonObject& o, const char* key, std::size_t stages) {
  std::vector<DcaeAct> out;
  for (const auto& s : o.strings(key, stages)) out.push_back(o.parsed(key, s, dcae_act_from));
  return out;
}

inline void read_encoder(const JsonObject& e, DcaeConfig& c) {
  c.encoder_width_list = e.integers("width_list");
  c.encoder_depth_list = e.integers("depth_list");
  c.encoder_block_type = block_types(e);
  c.encoder_norm = e.parsed("norm", e.string("norm"), dcae_norm_from);
  c.encoder_act = e.parsed("act", e.string("act"), dcae_act_from);
  e.expect("downsample_block_type", "ConvPixelUnshuffle");
  e.expect("downsample_match_channel", true);
  e.expect("downsample_shortcut", "averaging");
  e.expect("out_norm", nullptr);
  e.expect("out_act", nullptr);
  e.expect("out_shortcut", "averaging");
  e.expect("double_latent", false);
}

inline void read_decoder(const JsonObject& d, DcaeConfig& c) {
  c.decoder_width_list = d.integers("width_list");
  c.decoder_depth_list = d.integers("depth_list");
  c.decoder_block_type = block_types(d);
  c.decoder_norm = norms(d, "norm", constants::dcae_stages);
  c.decoder_act = acts(d, "act", constants::dcae_stages);
  c.decoder_out_norm = d.parsed("out_norm", d.string("out_norm"), dcae_norm_from);
  c.decoder_out_act = d.parsed("out_act", d.string("out_act"), dcae_act_from);
  d.expect("in_shortcut", "duplicating");
  d.expect("upsample_block_type", "ConvPixelShuffle");
  d.expect("upsample_match_channel", true);
  d.expect("upsample_shortcut", "duplicating");
}

inline void read_temporal_block(const JsonObject& t, DcaeConfig& c) {
  c.temporal_blocks = t.integer("n_blocks");
  c.temporal_dim = t.integer("dim");
  c.temporal_heads = t.integer("n_heads");
  c.temporal_ffn_hidden = t.integer("ffn_hidden");
  c.temporal_rmsnorm_eps = t.number("rmsnorm_eps");
  c.temporal_rope_theta = t.number("rope_theta");
  const auto head_dim = t.integer("head_dim"), rope_dim = t.integer("rope_dim");
  EPONA_CHECK(c.temporal_heads > 0 && head_dim * c.temporal_heads == c.temporal_dim, t.where("head_dim"), " (",
              head_dim, ") times n_heads (", c.temporal_heads, ") must equal dim (", c.temporal_dim, ")");
  EPONA_CHECK(rope_dim == head_dim, t.where("rope_dim"), " (", rope_dim, ") must equal head_dim (", head_dim, ")");
}

// The image size and the world-model keys the DC-AE shares with it (plain-object format).
inline DcaeConfig dcae_from_world(const JsonObject& w, const WorldModelConfig& world) {
  DcaeConfig c;
  c.image_h = world.image_h;
  c.image_w = world.image_w;
  c.latent_channels = c.temporal_dim = world.vae_embed_dim;
  if (w.has("vae")) w.expect("vae", "DCAE_f32c32");
  if (w.has("add_encoder_temporal")) w.expect("add_encoder_temporal", false);
  if (w.has("add_decoder_temporal")) c.add_decoder_temporal = w.boolean("add_decoder_temporal");
  if (w.has("temporal_patch_size")) c.condition_frames = w.integer("temporal_patch_size");
  return c;
}
}  // namespace config_detail

// The world-model keys of the official config dict (extra keys are ignored).
inline WorldModelConfig world_model_config_from_json(const nlohmann::json& j, const std::string& source,
                                                     const std::string& path = "world_model_config") {
  const config_detail::JsonObject o(j, source, path);
  WorldModelConfig c;
  const auto hw = config_detail::image_size(o);
  c.image_h = hw[0];
  c.image_w = hw[1];
  c.downsample_size = o.integer("downsample_size");
  c.patch_size = o.integer("patch_size");
  c.vae_embed_dim = o.integer("vae_embed_dim");
  c.condition_frames = o.integer("condition_frames");
  c.block_size = o.integer("block_size");
  c.n_layer = o.integers_n<3>("n_layer");
  c.n_head = o.integer("n_head");
  c.n_embd = o.integer("n_embd");
  c.n_embd_dit = o.integer("n_embd_dit");
  c.n_head_dit = o.integer("n_head_dit");
  c.axes_dim_dit = o.integers_n<3>("axes_dim_dit");
  c.n_layer_traj = o.integers_n<2>("n_layer_traj");
  c.n_embd_dit_traj = o.integer("n_embd_dit_traj");
  c.n_head_dit_traj = o.integer("n_head_dit_traj");
  c.axes_dim_dit_traj = o.integers_n<3>("axes_dim_dit_traj");
  c.traj_len = o.integer("traj_len");
  c.pose_x_vocab_size = o.integer("pose_x_vocab_size");
  c.pose_y_vocab_size = o.integer("pose_y_vocab_size");
  c.yaw_vocab_size = o.integer("yaw_vocab_size");
  c.pose_x_bound = o.number("pose_x_bound");
  c.pose_y_bound = o.number("pose_y_bound");
  c.yaw_bound = o.number("yaw_bound");
  c.num_sampling_steps = o.integer("num_sampling_steps");
  return c;
}

// The golden `dcae` section: {config: <dc-ae config dict>, image_size: [H, W], temporal_block: {...}}.
inline DcaeConfig dcae_config_from_json(const nlohmann::json& j, const std::string& source,
                                        const std::string& path = "dcae") {
  const config_detail::JsonObject section(j, source, path);
  const auto o = section.object("config");
  DcaeConfig c;
  c.in_channels = o.integer("in_channels");
  c.latent_channels = o.integer("latent_channels");
  const auto enc = o.object("encoder"), dec = o.object("decoder");
  for (const auto* side : {&enc, &dec}) {
    EPONA_CHECK(side->integer("in_channels") == c.in_channels, side->where("in_channels"),
                " differs from ", o.where("in_channels"));
    EPONA_CHECK(side->integer("latent_channels") == c.latent_channels, side->where("latent_channels"),
                " differs from ", o.where("latent_channels"));
  }
  config_detail::read_encoder(enc, c);
  config_detail::read_decoder(dec, c);
  o.expect("use_quant_conv", false);
  o.expect("add_encoder_temporal", false);
  c.add_decoder_temporal = o.boolean("add_decoder_temporal");
  c.condition_frames = o.integer("condition_frames");
  const auto hw = config_detail::image_size(section);
  c.image_h = hw[0];
  c.image_w = hw[1];
  config_detail::read_temporal_block(section.object("temporal_block"), c);
  const auto tokens = o.integer("token_size");
  if (c.image_h > 0 && c.image_w > 0)
    EPONA_CHECK(tokens == c.token_size(), o.where("token_size"), " (", tokens, ") does not match image_size ",
                c.image_h, "x", c.image_w, " (", c.token_size(), " latent tokens)");
  return c;
}

// The optional "planner" block: {"hypotheses": K (1..max_hypotheses), "choose": "medoid" | "mean"}.
inline model::PlanningRule planning_rule_from_json(const config_detail::JsonObject& p) {
  p.only_keys({"hypotheses", "choose"});
  model::PlanningRule r;
  if (p.has("hypotheses")) r.hypotheses = p.integer("hypotheses");
  EPONA_CHECK(r.hypotheses >= 1 && r.hypotheses <= constants::max_hypotheses, p.where("hypotheses"),
              " must be 1..", constants::max_hypotheses, ", got ", r.hypotheses);
  if (p.has("choose")) {
    const std::string rule = p.string("choose");
    const std::optional<model::PlanChoice> choice = model::plan_choice_named(rule);
    EPONA_CHECK(choice, p.where("choose"), " must be \"medoid\" or \"mean\", got ", json_brief(nlohmann::json(rule)));
    r.choose = *choice;
  }
  return r;
}

// Either the golden layout (has "world_model_config") or a plain world-model object, from
// which the DC-AE gets its image size, latent width, clip length and temporal flag. Validated.
inline ModelConfigs configs_from_json(const nlohmann::json& j, const std::string& source) {
  const config_detail::JsonObject top(j, source, "");
  ModelConfigs c;
  if (top.has("world_model_config")) {
    c.world = world_model_config_from_json(j.at("world_model_config"), source);
    EPONA_CHECK(top.has("dcae"), source, ": missing key 'dcae' (the golden layout needs both sections)");
    c.dcae = dcae_config_from_json(j.at("dcae"), source);
    EPONA_CHECK(c.world.vae_embed_dim == c.dcae.latent_channels, source, ": world_model_config.vae_embed_dim (",
                c.world.vae_embed_dim, ") must equal dcae.config.latent_channels (", c.dcae.latent_channels, ")");
  } else {
    c.world = world_model_config_from_json(j, source, "");
    c.dcae = config_detail::dcae_from_world(top, c.world);
  }
  if (top.has("planner")) c.planner = planning_rule_from_json(top.object("planner"));
  auto validate = [&](auto& cfg) {
    try {
      model::validate_with_size(cfg);
    } catch (const Error& e) {
      fail(source, ": ", e.what());
    }
  };
  validate(c.world);
  validate(c.dcae);
  return c;
}

inline ModelConfigs parse_configs(std::string_view text, const std::string& source) {
  return configs_from_json(parse_json(text, source), source);
}

inline ModelConfigs load_configs(const std::string& path) {
  std::error_code ec;
  EPONA_CHECK(std::filesystem::exists(path, ec), path, ": config file does not exist");
  EPONA_CHECK(std::filesystem::is_regular_file(path, ec), path, ": not a regular file");
  std::ifstream in(path, std::ios::binary);
  EPONA_CHECK(in, path, ": cannot open config file");
  std::ostringstream text;
  text << in.rdbuf();
  EPONA_CHECK(!in.bad(), path, ": read error");
  return parse_configs(text.str(), path);
}

// ---- writing (the golden layout, so that load_configs(to_json(c)) == c) ----
inline nlohmann::json to_json(const WorldModelConfig& c) {
  return {{"image_size", {c.image_h, c.image_w}},
          {"downsample_size", c.downsample_size},
          {"patch_size", c.patch_size},
          {"vae_embed_dim", c.vae_embed_dim},
          {"condition_frames", c.condition_frames},
          {"block_size", c.block_size},
          {"n_layer", c.n_layer},
          {"n_head", c.n_head},
          {"n_embd", c.n_embd},
          {"n_embd_dit", c.n_embd_dit},
          {"n_head_dit", c.n_head_dit},
          {"axes_dim_dit", c.axes_dim_dit},
          {"n_layer_traj", c.n_layer_traj},
          {"n_embd_dit_traj", c.n_embd_dit_traj},
          {"n_head_dit_traj", c.n_head_dit_traj},
          {"axes_dim_dit_traj", c.axes_dim_dit_traj},
          {"traj_len", c.traj_len},
          {"pose_x_vocab_size", c.pose_x_vocab_size},
          {"pose_y_vocab_size", c.pose_y_vocab_size},
          {"yaw_vocab_size", c.yaw_vocab_size},
          {"pose_x_bound", c.pose_x_bound},
          {"pose_y_bound", c.pose_y_bound},
          {"yaw_bound", c.yaw_bound},
          {"num_sampling_steps", c.num_sampling_steps}};
}

namespace config_detail {
template <class E>
nlohmann::json names(const std::vector<E>& v) {
  nlohmann::json a = nlohmann::json::array();
  for (auto e : v) a.push_back(std::string(to_string(e)));
  return a;
}
}  // namespace config_detail

inline nlohmann::json to_json(const DcaeConfig& c) {
  using nlohmann::json;
  const json encoder = {{"in_channels", c.in_channels},
                        {"latent_channels", c.latent_channels},
                        {"width_list", c.encoder_width_list},
                        {"depth_list", c.encoder_depth_list},
                        {"block_type", config_detail::names(c.encoder_block_type)},
                        {"norm", std::string(to_string(c.encoder_norm))},
                        {"act", std::string(to_string(c.encoder_act))},
                        {"downsample_block_type", "ConvPixelUnshuffle"},
                        {"downsample_match_channel", true},
                        {"downsample_shortcut", "averaging"},
                        {"out_norm", nullptr},
                        {"out_act", nullptr},
                        {"out_shortcut", "averaging"},
                        {"double_latent", false}};
  const json decoder = {{"in_channels", c.in_channels},
                        {"latent_channels", c.latent_channels},
                        {"in_shortcut", "duplicating"},
                        {"width_list", c.decoder_width_list},
                        {"depth_list", c.decoder_depth_list},
                        {"block_type", config_detail::names(c.decoder_block_type)},
                        {"norm", config_detail::names(c.decoder_norm)},
                        {"act", config_detail::names(c.decoder_act)},
                        {"upsample_block_type", "ConvPixelShuffle"},
                        {"upsample_match_channel", true},
                        {"upsample_shortcut", "duplicating"},
                        {"out_norm", std::string(to_string(c.decoder_out_norm))},
                        {"out_act", std::string(to_string(c.decoder_out_act))}};
  const json config = {{"in_channels", c.in_channels},
                       {"latent_channels", c.latent_channels},
                       {"encoder", encoder},
                       {"decoder", decoder},
                       {"use_quant_conv", false},
                       {"add_encoder_temporal", false},
                       {"add_decoder_temporal", c.add_decoder_temporal},
                       {"condition_frames", c.condition_frames},
                       {"token_size", c.token_size()}};
  const std::int64_t head_dim = c.temporal_heads > 0 ? c.temporal_dim / c.temporal_heads : 0;
  const json temporal = {{"n_blocks", c.temporal_blocks},         {"dim", c.temporal_dim},
                         {"n_heads", c.temporal_heads},           {"head_dim", head_dim},
                         {"ffn_hidden", c.temporal_ffn_hidden},   {"rmsnorm_eps", c.temporal_rmsnorm_eps},
                         {"rope_dim", head_dim},                  {"rope_theta", c.temporal_rope_theta}};
  return {{"config", config}, {"image_size", {c.image_h, c.image_w}}, {"temporal_block", temporal}};
}

inline nlohmann::json to_json(const ModelConfigs& c) {
  auto world = to_json(c.world);
  world["vae"] = "DCAE_f32c32";
  world["add_encoder_temporal"] = false;
  world["add_decoder_temporal"] = c.dcae.add_decoder_temporal;
  world["temporal_patch_size"] = c.dcae.condition_frames;
  nlohmann::json j{{"world_model_config", world}, {"dcae", to_json(c.dcae)}};
  if (c.planner != model::PlanningRule{})
    j["planner"] = {{"hypotheses", c.planner.hypotheses}, {"choose", model::plan_choice_name(c.planner.choose)}};
  return j;
}

}  // namespace epona::io
