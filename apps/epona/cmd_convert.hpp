// apps/epona/cmd_convert.hpp — `epona convert`: rewrites a checkpoint (the official torch.save
// .pkl, or safetensors) as one safetensors file with the same keys, dtypes and bytes — a flat,
// memory-mappable form that any safetensors reader (and epona, faster) loads without a pickle.
#pragma once

#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include "activity.hpp"
#include "args.hpp"
#include "console.hpp"
#include "inspect.hpp"
#include "models.hpp"
#include "output_paths.hpp"
#include "epona/io/limits.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/safetensors.hpp"

namespace epona::app {

inline ArgParser convert_parser() {
  ArgParser p("epona convert", "IN OUT.safetensors [options]",
              "Writes the tensors of a checkpoint (official .pkl or .safetensors) to a safetensors file:\n"
              "same names, dtypes, shapes and bytes. The metadata records the source file name.");
  p.positionals(2, 2, "input and output files")
      .option("key", "NAME", "state dict inside a .pkl (e.g. model_state_dict, model)", "automatic")
      .flag("quiet", "no notes on stderr", 'q')
      .epilog("example:\n  epona convert dcae_td_20000.pkl dcae_td_20000.safetensors");
  return p;
}

// Bytes the tensors view, and the distinct bytes under them (the union of their ranges): a .pkl
// may view one storage through many tensors, which safetensors cannot share, so a 2 MB .pkl of
// 300 views wrote 600 MB. Repeats up to limits::kConvertRepeat x the distinct bytes (tied weights
// are 2x) plus a slack for small buffers are written; more is refused before anything is written.
struct ViewBytes {
  std::uint64_t total = 0, distinct = 0;
};
inline ViewBytes view_bytes(const io::TensorMap& m) {
  std::vector<std::pair<const std::byte*, const std::byte*>> ranges;
  ViewBytes v;
  for (const auto& [name, t] : m.entries()) {
    v.total += t.bytes.size();
    if (!t.bytes.empty()) ranges.emplace_back(t.bytes.data(), t.bytes.data() + t.bytes.size());
  }
  std::sort(ranges.begin(), ranges.end());
  const std::byte* covered = nullptr;  // end of the union so far
  for (const auto& [b, e] : ranges) {
    const std::byte* from = covered && b < covered ? covered : b;
    if (e > from) v.distinct += static_cast<std::uint64_t>(e - from), covered = e;
  }
  return v;
}

inline void check_view_amplification(const io::TensorMap& m, const std::string& in) {
  const ViewBytes v = view_bytes(m);
  const std::uint64_t allowed = io::limits::kConvertRepeat * v.distinct + io::limits::kConvertRepeatSlack;
  EPONA_CHECK(v.total <= allowed, in, ": its tensors view ", v.distinct, " distinct bytes of storage ",
              v.total / std::max<std::uint64_t>(v.distinct, 1), " times over (", v.total,
              " bytes as safetensors, which cannot share storage); convert writes at most ",
              io::limits::kConvertRepeat, "x the distinct bytes. Save the tensors with .clone() to convert them");
}

inline int run_convert(const ParsedArgs& a, const Console& con) {
  const std::string in = a.positionals()[0], out = a.positionals()[1];
  check_file(in, "input");
  EPONA_CHECK(std::filesystem::path(out).extension() == ".safetensors", "output ", out,
              ": the name must end in .safetensors");
  std::error_code ec;
  EPONA_CHECK(!std::filesystem::equivalent(in, out, ec), "output ", out, " is the input file");
  prepare_output_file(out, "output " + out);
  con.note("reading ", in);
  const io::TensorMap m = [&] {
    const Activity doing("reading " + in);
    return io::load_weights(in, a.text("key", ""));
  }();
  check_view_amplification(m, in);
  const Activity doing("writing " + out);
  io::save_safetensors(out, m, {{"converted_from", std::filesystem::path(in).filename().string()}});
  const CheckpointStats s = checkpoint_stats(m, 1);
  con.out << "wrote " << out << ": " << s.tensors << " tensors, " << epona::detail::human_bytes(s.bytes) << "\n";
  return 0;
}

}  // namespace epona::app
