// apps/epona/cmd_info.hpp — `epona info`: what checkpoint files hold (format, tensors, dtypes,
// parameters per module prefix, keys) and the configuration their shapes imply, compared with
// the configuration the other commands would use; optionally written out as a --config file.
#pragma once

#include <algorithm>
#include <cctype>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "activity.hpp"
#include "args.hpp"
#include "console.hpp"
#include "inspect.hpp"
#include "models.hpp"
#include "epona/core/printable.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/npy.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/io/sha256.hpp"
#include "epona/model/parameter_counts.hpp"

namespace epona::app {

// Tensor names and metadata come from the file: printed escaped (no ESC or NUL reaches the
// terminal) and cut; real names are under 200 bytes.
inline constexpr std::size_t kNameCut = 200;

inline ArgParser info_parser() {
  ArgParser p("epona info", "FILE... [options]",
              "Describes checkpoint files (official .pkl or .safetensors): tensor count, dtypes, parameters per\n"
              "module prefix, and the world-model / DC-AE configuration their shapes imply. Settings that no\n"
              "shape reveals (head count of the MST, image size, window length, ...) are listed as assumed.");
  p.positionals(1, 64, "checkpoint file(s)")
      .flag("keys", "list every tensor: name, dtype, shape")
      .option("depth", "N", "module prefix depth of the parameter table", "2")
      .option("key", "NAME", "state dict inside a .pkl (e.g. model_state_dict, model)", "automatic")
      .option("config", "FILE", "configuration to compare with",
              "configs.json beside the first file, else the shipped Epona configuration")
      .option("write-config", "FILE", "write the detected configuration (assumed values from --config) as JSON")
      .flag("sha256", "only print each file's SHA-256 (hex, as sha256sum prints it) and size; the tensors are not read")
      .option("expect-sha256", "HEX", "check the one FILE's SHA-256 against HEX (64 hex digits); fails when they differ")
      .flag("quiet", "no notes on stderr", 'q')
      .epilog("examples:\n  epona info world.pkl dcae_td_20000.pkl --write-config nuplan.json\n"
              "  epona info --sha256 pretrained/epona_nuplan.pkl\n"
              "  epona info pretrained/dcae_td_20000.pkl --expect-sha256 <the digest on the hub's file page>");
  return p;
}

inline std::string human_bytes_text(double b) { return epona::detail::human_bytes(b); }

inline std::string count_text(double n) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.0f", n);
  std::string s = buf, out;
  for (std::size_t i = 0; i < s.size(); ++i) {
    if (i && (s.size() - i) % 3 == 0) out += ',';
    out += s[i];
  }
  return n >= 1e6 ? out + " (" + epona::detail::human_count(n) + ")" : out;
}

inline void print_facts(std::ostream& out, const std::vector<Fact>& facts) {
  std::size_t w = 0;
  for (const auto& f : facts) w = std::max(w, f.field.size() + f.value.size() + 3);
  for (const auto& f : facts) {
    const std::string left = f.field + " = " + f.value;
    out << "    " << left << std::string(w - left.size() + 2, ' ') << "<- " << f.evidence << "\n";
  }
}

inline void print_comparison(std::ostream& out, const std::vector<std::string>& diffs, const std::string& base) {
  if (diffs.empty()) {
    out << "  matches " << base << "\n";
    return;
  }
  out << "  differs from " << base << " in:\n";
  for (const auto& d : diffs) out << "    " << d << "\n";
}

// Each prefix's parameters in the file beside the count the detected configuration implies,
// summed over its parameter tree (`parameter_list()`, built once). A configuration that does not
// validate has no tree: the note after the listing says why.
template <class List>
void print_prefix_counts(std::ostream& out, const io::TensorMap& m, const std::vector<std::string>& prefixes,
                         List&& parameter_list) {
  std::optional<nn::ParamList> list;
  try {
    list = parameter_list();
  } catch (const Error&) {
  }
  for (const auto& prefix : prefixes) {
    double n = 0;
    for (const auto& [name, t] : m.entries())
      if (starts_with(name, prefix) && !is_buffer(name)) n += double(t.numel());
    out << "    " << printable(prefix, kNameCut) << "* " << count_text(n) << " parameters; ";
    if (!list) {
      out << "the detected configuration does not validate (see the note below)\n";
      continue;
    }
    const double implied = list->learned_count(prefix);
    out << "the detected configuration implies " << count_text(implied) << (n == implied ? " (match)" : " (MISMATCH)")
        << "\n";
  }
}

inline void print_checkpoint(std::ostream& out, const std::string& path, const io::TensorMap& m, int depth,
                             bool keys) {
  const auto format = io::sniff_weight_format(path);
  out << path << "\n  format: "
      << (format == io::WeightFormat::TorchZip ? "PyTorch checkpoint (torch.save ZIP)" : "safetensors") << "\n";
  if (format == io::WeightFormat::Safetensors)
    for (const auto& [k, v] : io::read_safetensors(path).metadata) out << "  metadata: " << printable(k, kNameCut) << " = " << printable(v, kNameCut) << "\n";
  const CheckpointStats s = checkpoint_stats(m, depth);
  out << "  tensors: " << s.tensors << ", " << human_bytes_text(s.bytes) << " of data; dtypes:";
  for (const auto& [name, d] : s.dtypes) out << " " << d.first << " x " << name << " (" << human_bytes_text(d.second) << ")";
  out << "\n  parameters: " << count_text(s.parameters);
  if (s.buffer_elements > 0) out << " + " << count_text(s.buffer_elements) << " BatchNorm buffer elements";
  out << "\n  per module prefix:\n";
  std::size_t w = 0;
  for (const auto& [g, _] : s.groups) w = std::max(w, printable(g, kNameCut).size());
  for (const auto& [group, st] : s.groups) {
    const std::string g = printable(group, kNameCut);
    out << "    " << g << std::string(w - g.size() + 2, ' ') << count_text(st.parameters) << " parameters, " << st.tensors
        << " tensors, " << human_bytes_text(st.bytes) << "\n";
  }
  if (keys) {
    out << "  keys:\n";
    for (const auto& [name, t] : m.entries())
      out << "    " << printable(name, kNameCut) << "  " << dtype_name(t.dtype) << "  " << shape_str(t.shape) << "\n";
  }
}

inline void print_detection(std::ostream& out, const io::TensorMap& m, const Detection& d,
                            const io::ModelConfigs& base, const std::string& base_name) {
  if (!d.has_world && !d.has_dcae) {
    out << "  no world-model (module.*) or DC-AE (encoder.*, decoder.*) keys: not an Epona checkpoint\n";
    return;
  }
  if (d.has_world) {
    const auto& w = d.configs.world;
    out << "  world model (module.*), read from the shapes:\n";
    print_facts(out, d.world_facts);
    out << "  assumed (no shape shows them; from " << base_name << "): " << join(d.world_assumed, ", ") << "\n";
    print_comparison(out, world_differences(w, base.world), base_name);
    print_prefix_counts(out, m, {"module.model.", "module.dit.", "module.traj_dit."},
                        [&] { return model::world_parameter_list(w); });
  }
  if (d.has_dcae) {
    const auto& c = d.configs.dcae;
    out << "  DC-AE (encoder.*, decoder.*, temporal blocks), read from the shapes:\n";
    print_facts(out, d.dcae_facts);
    out << "  assumed (no shape shows them; from " << base_name << "): " << join(d.dcae_assumed, ", ") << "\n";
    print_comparison(out, dcae_differences(c, base.dcae), base_name);
    print_prefix_counts(out, m, {"encoder.", "decoder.", "causal_time_block.", "space_block."},
                        [&] { return model::dcae_parameter_list(c); });
  }
  for (const auto& p : d.problems) out << "  cannot read: " << printable(p, 4 * kNameCut) << "\n";
}

// The configuration to compare with: --config, else a configs.json beside the first file (how
// a trained model ships, e.g. models/small-synthetic), else the released model's.
inline std::string info_base_path(const ParsedArgs& a) {
  if (a.has("config")) return *a.get("config");
  const auto beside = std::filesystem::path(a.positionals().front()).parent_path() / "configs.json";
  std::error_code ec;
  return std::filesystem::is_regular_file(beside, ec) ? beside.string() : "";
}

// --expect-sha256 as lowercase hex, refused (before any hashing) unless it is 64 hex digits.
inline std::string expected_sha256(const ParsedArgs& a) {
  std::string hex = *a.get("expect-sha256");
  const bool digits = std::all_of(hex.begin(), hex.end(), [](unsigned char c) { return std::isxdigit(c) != 0; });
  if (hex.size() != 64 || !digits)
    usage_fail("--expect-sha256 needs a SHA-256 digest, 64 hex digits; got '", printable(hex, 100), "' (",
               hex.size(), " characters)");
  for (auto& c : hex) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (a.positionals().size() != 1)
    usage_fail("--expect-sha256 checks one file; got ", a.positionals().size(), " files");
  return hex;
}

// Files from this size on show progress while hashed (a second or more on a fast disk).
inline constexpr std::uint64_t kHashProgressBytes = std::uint64_t{256} << 20;

// The SHA-256 of one file, streamed, with progress on stderr (in MB) for large files.
inline std::string file_sha256(const std::string& path, std::uint64_t size, const Console& con) {
  const Activity doing("hashing " + path);
  if (size < kHashProgressBytes) return io::hex(io::sha256_file(path));
  constexpr std::uint64_t kMB = 1'000'000;
  Progress bar(con, "sha256 " + std::filesystem::path(path).filename().string(),
               static_cast<std::int64_t>((size + kMB - 1) / kMB), "MB");
  std::int64_t shown = 0;
  return io::hex(io::sha256_file(path, [&](std::uint64_t done, std::uint64_t) {
    const auto mb = static_cast<std::int64_t>(done == size ? (size + kMB - 1) / kMB : done / kMB);
    if (mb > shown) bar.advance(mb - shown), shown = mb;
  }));
}

// --sha256 / --expect-sha256: "<hex>  <path>  <bytes> bytes (<size>)" per file; with
// --expect-sha256, a mismatch is an error naming both digests. The tensors are not read: a
// truncated download fails here with its digest rather than with a parse error.
inline int run_info_sha256(const ParsedArgs& a, const Console& con) {
  for (const char* other : {"keys", "write-config", "config", "key", "depth"})
    if (a.has(other))
      usage_fail("--", other, " describes the tensors, which --sha256/--expect-sha256 do not read; run epona info "
                 "again without them");
  const std::string expected = a.has("expect-sha256") ? expected_sha256(a) : "";
  for (const auto& path : a.positionals()) check_file(path, "checkpoint");
  for (const auto& path : a.positionals()) {
    const auto size = static_cast<std::uint64_t>(std::filesystem::file_size(path));
    const std::string digest = file_sha256(path, size, con);
    con.out << digest << "  " << path << "  " << grouped(static_cast<std::int64_t>(size)) << " bytes ("
            << human_bytes_text(double(size)) << ")\n";
    con.out.flush();
    EPONA_CHECK(expected.empty() || digest == expected, path, ": SHA-256 mismatch: the file's is ", digest,
                ", --expect-sha256 gave ", expected,
                " (an incomplete or damaged download, or another file: fetch it again, and check the digest is "
                "the one of this file)");
    if (!expected.empty()) con.note("SHA-256 matches --expect-sha256: ", path, " is intact");
  }
  return 0;
}

inline int run_info(const ParsedArgs& a, const Console& con) {
  if (a.flag("sha256") || a.has("expect-sha256")) return run_info_sha256(a, con);
  const int depth = static_cast<int>(a.integer("depth", 2, 1, 64));
  const std::string base_path = info_base_path(a);
  if (!base_path.empty() && !a.has("config")) con.note("comparing with ", base_path, " (beside the weights)");
  const io::ModelConfigs base = base_path.empty() ? io::ModelConfigs{} : io::load_configs(base_path);
  const std::string base_name = base_path.empty() ? "the shipped Epona configuration" : base_path;
  io::ModelConfigs combined = base;  // world part from the file holding it, DC-AE from the other
  for (const auto& path : a.positionals()) {
    check_file(path, "checkpoint");
    con.note("reading ", path);
    const bool pkl = io::sniff_weight_format(path) != io::WeightFormat::Safetensors;
    const io::TensorMap m = io::load_weights(path, pkl ? a.text("key", "") : "");
    print_checkpoint(con.out, path, m, depth, a.flag("keys"));
    const Detection d = detect_configuration(m, base);
    print_detection(con.out, m, d, base, base_name);
    if (d.has_world) combined.world = d.configs.world;
    if (d.has_dcae) combined.dcae = d.configs.dcae;
  }
  for (const auto* what : {"world model", "DC-AE"}) {
    try {
      std::string(what) == "DC-AE" ? model::validate_with_size(combined.dcae) : model::validate_with_size(combined.world);
    } catch (const Error& e) {
      // The shapes are what they are: what does not fit is a value assumed from the base.
      con.out << "note: the " << what << " read from the shapes does not fit the values assumed from " << base_name
              << ": " << e.what() << "\n      give the model's configs.json with --config (or write one with "
              << "--write-config, fix the assumed values, and pass it)\n";
    }
  }
  if (a.has("write-config")) {
    const std::string path = *a.get("write-config");
    io::write_atomically(path, io::to_json(combined).dump(1) + "\n");
    con.out << "wrote the detected configuration to " << path << " (check the assumed values, then pass it with --config)\n";
  }
  return 0;
}

}  // namespace epona::app
