// apps/epona/inspect.hpp — what a checkpoint holds and which configuration its shapes imply:
// tensor/dtype/parameter statistics per module prefix, and the world-model / DC-AE settings
// that can be read from weight shapes and key counts. Settings no shape reveals (the MST head
// count, image size, window length, vocabularies, activations, ...) are taken from a base
// configuration and listed as assumed.
#pragma once

#include <charconv>
#include <cstdint>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "epona/domain/config_json.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config.hpp"

namespace epona::app {

// ---- statistics -----------------------------------------------------------------------

inline bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}
inline bool starts_with(const std::string& s, const std::string& prefix) { return s.rfind(prefix, 0) == 0; }
inline bool is_index(const std::string& s) {
  return !s.empty() && s.find_first_not_of("0123456789") == std::string::npos;
}

// BatchNorm statistics are stored with the weights but are not learned parameters.
inline bool is_buffer(const std::string& name) {
  return ends_with(name, ".running_mean") || ends_with(name, ".running_var") || ends_with(name, ".num_batches_tracked");
}

// The first `depth` dotted components of a key, stopping before a numeric one
// ("causal_time_block.3.attention.wq.weight" -> "causal_time_block" at any depth >= 1).
inline std::string group_of(const std::string& name, int depth) {
  std::string group;
  std::size_t start = 0;
  for (int d = 0; d < depth; ++d) {
    const std::size_t dot = name.find('.', start);
    const std::string part = name.substr(start, dot == std::string::npos ? std::string::npos : dot - start);
    if (is_index(part) || dot == std::string::npos) break;  // the last component is a tensor, not a module
    group += (group.empty() ? "" : ".") + part;
    start = dot + 1;
  }
  return group.empty() ? "(top level)" : group;
}

struct GroupStats {
  std::int64_t tensors = 0;
  double parameters = 0, buffer_elements = 0, bytes = 0;
};

struct CheckpointStats {
  std::int64_t tensors = 0;
  double parameters = 0, buffer_elements = 0, bytes = 0;
  std::map<std::string, std::pair<std::int64_t, double>> dtypes;  // name -> (tensors, bytes)
  std::map<std::string, GroupStats> groups;
};

inline CheckpointStats checkpoint_stats(const io::TensorMap& m, int depth) {
  CheckpointStats s;
  for (const auto& [name, t] : m.entries()) {
    const double n = double(t.numel()), bytes = double(t.bytes.size());
    auto& g = s.groups[group_of(name, depth)];
    auto& d = s.dtypes[std::string(dtype_name(t.dtype))];
    ++s.tensors, ++g.tensors, ++d.first;
    s.bytes += bytes, g.bytes += bytes, d.second += bytes;
    if (is_buffer(name)) {
      s.buffer_elements += n, g.buffer_elements += n;
    } else {
      s.parameters += n, g.parameters += n;
    }
  }
  return s;
}

// ---- configuration from shapes ---------------------------------------------------------

struct Fact {
  std::string field, value, evidence;  // evidence: the key (and shape) the value was read from
};

struct Detection {
  bool has_world = false, has_dcae = false;
  io::ModelConfigs configs;              // the base with every readable field replaced
  std::vector<Fact> world_facts, dcae_facts;
  std::vector<std::string> world_assumed, dcae_assumed;  // fields no shape reveals
  std::vector<std::string> problems;     // what could not be read although the part is present
};

namespace inspect_detail {

inline std::optional<Shape> shape_of(const io::TensorMap& m, const std::string& key) {
  if (!m.contains(key)) return std::nullopt;
  return m.at(key).shape;
}

// Distinct indices i of keys "<prefix><i>.<...>".
inline std::set<std::int64_t> indices(const io::TensorMap& m, const std::string& prefix) {
  std::set<std::int64_t> out;
  for (const auto& [name, t] : m.entries()) {
    if (!starts_with(name, prefix)) continue;
    const std::size_t dot = name.find('.', prefix.size());
    const std::string part = name.substr(prefix.size(), dot == std::string::npos ? std::string::npos : dot - prefix.size());
    std::int64_t i = 0;
    if (dot != std::string::npos && is_index(part) && part.size() < 10 &&
        std::from_chars(part.data(), part.data() + part.size(), i).ec == std::errc())
      out.insert(i);
  }
  return out;
}

// Reads shapes into one configuration, recording each value with the key it came from.
class Reader {
 public:
  Reader(const io::TensorMap& m, std::vector<Fact>& facts, std::vector<std::string>& problems)
      : m_(m), facts_(facts), problems_(problems) {}

  // Dimension `dim` of `key` into `out`; false (and a problem) if the key is absent or too short.
  bool dim(const std::string& key, int dim, std::int64_t& out, const std::string& field, std::int64_t scale = 1) {
    const auto s = shape_of(m_, key);
    if (!s || static_cast<int>(s->size()) <= dim) {
      problems_.push_back(field + ": cannot be read (no tensor '" + key + "' with " + std::to_string(dim + 1) +
                          "+ dimensions)");
      return false;
    }
    out = (*s)[static_cast<std::size_t>(dim)] * scale;
    facts_.push_back({field, std::to_string(out), key + " " + shape_str(*s)});
    return true;
  }
  // The number of blocks "<prefix>0." ... "<prefix>(n-1)." (they must be numbered without gaps).
  std::int64_t count(const std::string& prefix, const std::string& field) {
    const auto idx = indices(m_, prefix);
    const auto n = static_cast<std::int64_t>(idx.size());
    if (n > 0 && *idx.rbegin() != n - 1)
      problems_.push_back(field + ": blocks under '" + prefix + "' are not numbered 0.." + std::to_string(n - 1));
    facts_.push_back({field, std::to_string(n), n ? prefix + "0.." + std::to_string(n - 1) : "no key '" + prefix + "*'"});
    return n;
  }
  void note(const std::string& field, const std::string& value, const std::string& evidence) {
    facts_.push_back({field, value, evidence});
  }
  bool has(const std::string& key) const { return m_.contains(key); }

 private:
  const io::TensorMap& m_;
  std::vector<Fact>& facts_;
  std::vector<std::string>& problems_;
};

// A FLUX DiT's width, depths and head count (the QK-norm scale has head_dim entries).
inline void read_dit(Reader& r, const std::string& p, const std::string& in_key, std::int64_t& width,
                     std::int64_t& doubles, std::int64_t& singles, std::int64_t& heads, const std::string& name) {
  r.dim(p + in_key, 0, width, name + " width");
  doubles = r.count(p + "double_blocks.", name + " double blocks");
  singles = r.count(p + "single_blocks.", name + " single blocks");
  const std::string qn = doubles > 0 ? p + "double_blocks.0.img_attn.norm.query_norm.scale"
                                     : p + "single_blocks.0.norm.query_norm.scale";
  std::int64_t head_dim = 0;
  if (r.dim(qn, 0, head_dim, name + " head dim") && head_dim > 0 && width % head_dim == 0) {
    heads = width / head_dim;
    r.note(name + " heads", std::to_string(heads), "width / head dim");
  }
}

inline void read_world(const io::TensorMap& m, Detection& d) {
  auto& w = d.configs.world;
  Reader r(m, d.world_facts, d.problems);
  const std::string mst = "module.model.";
  r.dim(mst + "time_emb", 1, w.n_embd, "MST width n_embd");
  r.dim(mst + "img_projector.0.weight", 1, w.vae_embed_dim, "vae_embed_dim (latent channels per token)");
  w.n_layer[0] = r.count(mst + "causal_time_space_blocks.", "MST blocks n_layer[0]");
  read_dit(r, "module.dit.", "img_in.weight", w.n_embd_dit, w.n_layer[1], w.n_layer[2], w.n_head_dit, "VisDiT");
  read_dit(r, "module.traj_dit.", "traj_in.weight", w.n_embd_dit_traj, w.n_layer_traj[0], w.n_layer_traj[1],
           w.n_head_dit_traj, "TrajDiT");
  d.world_assumed = {"n_head (MST heads: its q/k norms span the whole width)", "image_size", "condition_frames",
                     "axes_dim_dit", "axes_dim_dit_traj", "traj_len", "pose/yaw vocab sizes", "pose/yaw bounds",
                     "num_sampling_steps"};
}

// One DC-AE stage: its blocks (ResBlock: main.conv1; EViT: context_module), their width, type and
// norm (BatchNorm when running statistics are stored).
struct StageRead {
  std::int64_t depth = 0, width = 0;
  std::optional<DcaeBlockType> type;
  std::optional<DcaeNorm> norm;
};

inline StageRead read_stage(const io::TensorMap& m, const std::string& stage_prefix) {
  StageRead s;
  for (std::int64_t i : indices(m, stage_prefix)) {
    const std::string b = stage_prefix + std::to_string(i) + ".";
    std::optional<Shape> shape;
    if ((shape = shape_of(m, b + "main.conv1.conv.weight"))) {
      s.type = DcaeBlockType::ResBlock;
      s.width = (*shape)[0];
      s.norm = m.contains(b + "main.conv2.norm.running_mean") ? DcaeNorm::BatchNorm2d : DcaeNorm::TritonRms2d;
    } else if ((shape = shape_of(m, b + "context_module.main.qkv.conv.weight"))) {
      s.type = DcaeBlockType::EViT_GLU;
      s.width = shape->size() > 1 ? (*shape)[1] : 0;
      s.norm = m.contains(b + "context_module.main.proj.norm.running_mean") ? DcaeNorm::BatchNorm2d
                                                                             : DcaeNorm::TritonRms2d;
    } else {
      continue;  // a resampling block
    }
    ++s.depth;
  }
  return s;
}

inline std::string list_text(const std::vector<std::int64_t>& v) {
  std::string s = "[";
  for (std::size_t i = 0; i < v.size(); ++i) s += (i ? ", " : "") + std::to_string(v[i]);
  return s + "]";
}
template <class E>
std::string names_text(const std::vector<E>& v) {
  std::string s = "[";
  for (std::size_t i = 0; i < v.size(); ++i) s += (i ? ", " : "") + std::string(to_string(v[i]));
  return s + "]";
}

inline void read_dcae_side(const io::TensorMap& m, Detection& d, bool encoder) {
  auto& c = d.configs.dcae;
  const std::string side = encoder ? "encoder" : "decoder";
  auto& width = encoder ? c.encoder_width_list : c.decoder_width_list;
  auto& depth = encoder ? c.encoder_depth_list : c.decoder_depth_list;
  auto& type = encoder ? c.encoder_block_type : c.decoder_block_type;
  std::vector<DcaeNorm> norms = encoder ? std::vector<DcaeNorm>(6, c.encoder_norm) : c.decoder_norm;
  for (std::size_t s = 1; s < 6 && s < width.size(); ++s) {
    const StageRead r = read_stage(m, side + ".stages." + std::to_string(s) + ".op_list.");
    depth[s] = r.depth;
    if (r.depth > 0) width[s] = r.width, type[s] = *r.type, norms[s] = *r.norm;
  }
  const std::string where = side + ".stages.*.op_list.* block keys";
  d.dcae_facts.push_back({side + " width_list[1..5]", list_text(std::vector<std::int64_t>(width.begin() + 1, width.end())), where});
  d.dcae_facts.push_back({side + " depth_list", list_text(depth), where});
  d.dcae_facts.push_back({side + " block_type", names_text(type), "ResBlock: main.conv1, EViT_GLU: context_module"});
  if (encoder) {
    c.encoder_norm = norms[1];
    d.dcae_facts.push_back({"encoder norm", std::string(to_string(c.encoder_norm)), "running_mean present: bn2d"});
  } else {
    c.decoder_norm = norms;
    d.dcae_facts.push_back({"decoder norm", names_text(norms), "running_mean present: bn2d"});
    c.decoder_out_norm = m.contains("decoder.project_out.op_list.0.running_mean") ? DcaeNorm::BatchNorm2d
                                                                                   : DcaeNorm::TritonRms2d;
    d.dcae_facts.push_back({"decoder out_norm", std::string(to_string(c.decoder_out_norm)), "decoder.project_out.op_list.0"});
  }
}

inline void read_dcae(const io::TensorMap& m, Detection& d) {
  auto& c = d.configs.dcae;
  Reader r(m, d.dcae_facts, d.problems);
  r.dim("encoder.project_in.conv.conv.weight", 1, c.in_channels, "in_channels");
  r.dim("encoder.project_out.main.op_list.0.conv.weight", 0, c.latent_channels, "latent_channels");
  read_dcae_side(m, d, true);
  read_dcae_side(m, d, false);
  c.temporal_blocks = r.count("causal_time_block.", "temporal blocks (time + space pairs)");
  c.add_decoder_temporal = c.temporal_blocks > 0;
  if (c.add_decoder_temporal) {
    r.dim("causal_time_block.0.attention.wq.weight", 0, c.temporal_dim, "temporal dim");
    r.dim("causal_time_block.0.feed_forward.w1.weight", 0, c.temporal_ffn_hidden, "temporal ffn_hidden");
  }
  d.dcae_assumed = {"encoder/decoder activations", "temporal n_heads", "temporal clip length (condition_frames)",
                    "image_size", "width_list[0]"};
}

}  // namespace inspect_detail

// Which parts a weight map holds, and the configuration its shapes imply on top of `base`.
inline Detection detect_configuration(const io::TensorMap& m, const io::ModelConfigs& base) {
  Detection d;
  d.configs = base;
  for (const auto& name : m.names()) {
    d.has_world = d.has_world || starts_with(name, "module.");
    d.has_dcae = d.has_dcae || starts_with(name, "encoder.") || starts_with(name, "decoder.");
  }
  if (d.has_world) inspect_detail::read_world(m, d);
  if (d.has_dcae) inspect_detail::read_dcae(m, d);
  return d;
}

// "key: a (checkpoint) vs b (configuration)" for every field where two JSON objects differ.
inline void json_differences(const nlohmann::json& a, const nlohmann::json& b, const std::string& path,
                             std::vector<std::string>& out) {
  if (a.is_object() && b.is_object()) {
    for (auto it = a.begin(); it != a.end(); ++it) {
      const std::string key = path.empty() ? it.key() : path + "." + it.key();
      if (b.contains(it.key()))
        json_differences(it.value(), b.at(it.key()), key, out);
      else
        out.push_back(key + ": missing in the configuration");
    }
    return;
  }
  if (a != b) out.push_back(path + ": " + a.dump() + " (checkpoint) vs " + b.dump() + " (configuration)");
}

inline std::vector<std::string> world_differences(const WorldModelConfig& checkpoint, const WorldModelConfig& config) {
  std::vector<std::string> out;
  json_differences(io::to_json(checkpoint), io::to_json(config), "", out);
  return out;
}
inline std::vector<std::string> dcae_differences(const DcaeConfig& checkpoint, const DcaeConfig& config) {
  std::vector<std::string> out;
  json_differences(io::to_json(checkpoint), io::to_json(config), "", out);
  return out;
}

}  // namespace epona::app
