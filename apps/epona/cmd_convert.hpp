// apps/epona/cmd_convert.hpp — `epona convert`: rewrites a checkpoint (the official torch.save
// .pkl, or safetensors) as one safetensors file with the same keys, dtypes and bytes — a flat,
// memory-mappable form that any safetensors reader (and epona, faster) loads without a pickle.
#pragma once

#include <filesystem>
#include <string>

#include "activity.hpp"
#include "args.hpp"
#include "console.hpp"
#include "inspect.hpp"
#include "models.hpp"
#include "output_paths.hpp"
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
  const Activity doing("writing " + out);
  io::save_safetensors(out, m, {{"converted_from", std::filesystem::path(in).filename().string()}});
  const CheckpointStats s = checkpoint_stats(m, 1);
  con.out << "wrote " << out << ": " << s.tensors << " tensors, " << epona::detail::human_bytes(s.bytes) << "\n";
  return 0;
}

}  // namespace epona::app
