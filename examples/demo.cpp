// epona demo (first stage): loads the bundled conformance model — configs.json and the world-model
// and DC-AE safetensors — and prints what it found: the configuration, tensor counts, dtypes,
// and parameter counts per module prefix checked against the counts the configuration implies.
//
// usage: example_demo [golden_dir]        (default: tests/data/golden, relative to the cwd)
#include <cstdio>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "epona/io/config_json.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/model/config.hpp"

namespace {

struct PrefixCount {
  const char* prefix;
  double config_count;  // what the configuration implies (learnable parameters)
};

// BatchNorm statistics are stored with the weights but are not learned parameters.
bool is_buffer(const std::string& name) {
  for (const std::string suffix : {".running_mean", ".running_var", ".num_batches_tracked"})
    if (name.size() >= suffix.size() && name.compare(name.size() - suffix.size(), suffix.size(), suffix) == 0)
      return true;
  return false;
}

double count_prefix(const epona::io::TensorMap& m, const std::string& prefix, bool buffers) {
  double n = 0;
  for (const auto& [name, t] : m.entries())
    if (name.rfind(prefix, 0) == 0 && is_buffer(name) == buffers) n += double(t.numel());
  return n;
}

void print_file(const std::string& label, const epona::io::SafetensorsFile& f) {
  std::map<std::string, std::size_t> dtypes;
  std::size_t bytes = 0;
  for (const auto& [name, t] : f.tensors.entries()) {
    ++dtypes[std::string(epona::dtype_name(t.dtype))];
    bytes += t.bytes.size();
  }
  std::printf("%s: %zu tensors, %.2f MB of data;", label.c_str(), f.tensors.size(), double(bytes) / 1e6);
  for (const auto& [dtype, n] : dtypes) std::printf(" %zu x %s", n, dtype.c_str());
  std::printf("\n");
  for (const auto& [k, v] : f.metadata) std::printf("  metadata %s = %s\n", k.c_str(), v.c_str());
}

// Prints each prefix's count; false if any differs from what the configuration implies.
bool print_prefixes(const epona::io::TensorMap& m, const std::vector<PrefixCount>& prefixes) {
  bool all_match = true;
  for (const auto& p : prefixes) {
    const double loaded = count_prefix(m, p.prefix, false);
    std::printf("  %-20s %14.0f parameters  (config implies %.0f: %s)\n", p.prefix, loaded, p.config_count,
                loaded == p.config_count ? "match" : "MISMATCH");
    all_match = all_match && loaded == p.config_count;
  }
  return all_match;
}

void print_config(const epona::io::ModelConfigs& c) {
  const auto& w = c.world;
  std::printf("world model: image %lldx%lld -> latent %lldx%lld (L = %lld tokens, %lld per frame), F = %lld frames\n",
              (long long)w.image_h, (long long)w.image_w, (long long)w.latent_h(), (long long)w.latent_w(),
              (long long)w.img_tokens(), (long long)w.tokens_per_frame(), (long long)w.condition_frames);
  std::printf("  MST %lld blocks, width %lld, %lld heads | VisDiT %lld+%lld blocks, width %lld, %lld heads |"
              " TrajDiT %lld+%lld blocks, width %lld, %lld heads | traj_len %lld, %lld sampling steps\n",
              (long long)w.mst_depth(), (long long)w.n_embd, (long long)w.n_head, (long long)w.vis_double_blocks(),
              (long long)w.vis_single_blocks(), (long long)w.n_embd_dit, (long long)w.n_head_dit,
              (long long)w.traj_double_blocks(), (long long)w.traj_single_blocks(), (long long)w.n_embd_dit_traj,
              (long long)w.n_head_dit_traj, (long long)w.traj_len, (long long)w.num_sampling_steps);
  const auto& d = c.dcae;
  std::printf("DC-AE: image %lldx%lld -> latent %lldx%lldx%lld, widths", (long long)d.image_h, (long long)d.image_w,
              (long long)d.latent_channels, (long long)d.latent_h(), (long long)d.latent_w());
  for (auto v : d.encoder_width_list) std::printf(" %lld", (long long)v);
  std::printf(", temporal decoder %s (%lld-frame clips)\n", d.add_decoder_temporal ? "on" : "off",
              (long long)d.condition_frames);
}

}  // namespace

int main(int argc, char** argv) {
  const std::string dir = argc > 1 ? argv[1] : "tests/data/golden";
  if (argc > 2 || (argc == 2 && (std::string(argv[1]) == "-h" || std::string(argv[1]) == "--help"))) {
    std::printf("usage: %s [golden_dir]   (default: tests/data/golden)\n", argv[0]);
    return argc > 2 ? 2 : 0;
  }
  try {
    if (!std::filesystem::is_directory(dir))
      epona::fail("model directory '", dir, "' not found (run from the repository root, or pass the directory "
                  "holding configs.json and the .safetensors files as the first argument)");
    const auto configs = epona::io::load_configs(dir + "/configs.json");
    print_config(configs);

    const auto world = epona::io::read_safetensors(dir + "/weights_world.safetensors");
    print_file("weights_world.safetensors", world);
    bool consistent = print_prefixes(world.tensors, {{"module.model.", configs.world.mst_parameter_count()},
                                   {"module.dit.", configs.world.vis_dit_parameter_count()},
                                   {"module.traj_dit.", configs.world.traj_dit_parameter_count()}});

    const auto dcae = epona::io::read_safetensors(dir + "/weights_dcae.safetensors");
    print_file("weights_dcae.safetensors", dcae);
    const double temporal_half = configs.dcae.temporal_parameter_count() / 2;  // time and space blocks
    consistent = print_prefixes(dcae.tensors, {{"encoder.", configs.dcae.encoder_parameter_count()},
                                  {"decoder.", configs.dcae.decoder_parameter_count()},
                                  {"causal_time_block.", temporal_half},
                                  {"space_block.", temporal_half}}) && consistent;
    std::printf("  (plus %.0f BatchNorm buffer elements; config implies %.0f)\n",
                count_prefix(dcae.tensors, "", true), configs.dcae.buffer_count());
    if (!consistent) epona::fail("the weights do not match the configuration in ", dir, "/configs.json");
    return 0;
  } catch (const epona::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
