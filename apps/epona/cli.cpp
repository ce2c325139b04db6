// apps/epona/cli.cpp — the `epona` program's commands (apps/epona/cli.hpp declares `run`). The
// one translation unit that compiles them: the models, the loaders and every command's code.

#include <exception>
#include <filesystem>
#include <iostream>
#include <new>
#include <string>
#include <vector>

#include "activity.hpp"
#include "args.hpp"
#include "cmd_codec.hpp"
#include "cmd_convert.hpp"
#include "cmd_eval.hpp"
#include "cmd_generate.hpp"
#include "cmd_info.hpp"
#include "cmd_plan.hpp"
#include "cmd_synth.hpp"
#include "cli.hpp"
#include "console.hpp"
#include "engine.hpp"
#include "processes.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/trajectory_io.hpp"

namespace epona::app {
namespace {

struct Subcommand {
  const char* name;
  const char* summary;
  ArgParser (*parser)();
  int (*run)(const ParsedArgs&, const Console&);
};

const std::vector<Subcommand>& subcommands() {
  static const std::vector<Subcommand> list = {
      {"plan", "plan the ego trajectory from the last frames and poses (JSON/CSV + a picture)", plan_parser, run_plan},
      {"generate", "roll out N frames under the model's own plan or given actions", generate_parser, run_generate},
      {"encode", "images -> DC-AE latents (.npy)", encode_parser, run_encode},
      {"decode", "DC-AE latents (.npy) -> PNG frames", decode_parser, run_decode},
      {"info", "what a checkpoint holds and the configuration its shapes imply", info_parser, run_info},
      {"eval", "scores the model on a clip set: planning L2/collisions, video PSNR/SSIM, with baselines", eval_parser, run_eval},
      {"convert", "a checkpoint (.pkl or .safetensors) -> .safetensors, same tensors or --dtype bfloat16", convert_parser, run_convert},
      {"synth", "driving clips from a procedural world (frames, poses, boxes) for training and evaluation", synth_parser, run_synth},
  };
  return list;
}

// The commands that load a network, which take --backend, --dtype and --threads.
bool runs_a_model(const std::string& name) {
  for (const char* c : {"plan", "generate", "encode", "decode", "eval"})
    if (name == c) return true;
  return false;
}

std::string main_help() {
  std::string s =
      "usage: epona <command> [options]\n\n"
      "Runs the Epona world model (ICCV 2025) from its released checkpoints: plans trajectories, rolls\n"
      "out driving video, encodes and decodes frames. Without --weights, plan and generate run a small\n"
      "bundled model (a small Epona trained on a synthetic driving world) on its demo clip.\n\ncommands:\n";
  for (const auto& c : subcommands()) s += "  " + std::string(c.name) + std::string(10 - std::string(c.name).size(), ' ') + c.summary + "\n";
  s += "\n`epona <command> --help` shows the options of a command.\n";
  return s;
}

}  // namespace

std::unique_ptr<Engine> make_engine(const ComputeOptions& c) {
#if defined(EPONA_APP_CUDA)
  if (c.backend == "cuda") return make_cuda_engine(c);
#endif
  check_backend(c.backend);
  return c.bf16_weights ? make_cpu_engine<bf16>(c) : make_cpu_engine<float>(c);
}

int run(const std::vector<std::string>& args, std::ostream& out, std::ostream& err, bool interactive) {
  try {
    if (args.empty() || args[0] == "--help" || args[0] == "-h" || args[0] == "help") {
      (args.empty() ? err : out) << main_help();
      if (args.empty()) usage_fail("no command given (plan, generate, eval, encode, decode, info, convert, synth)");
      return 0;
    }
    if (args[0] == "--version") {
      out << "epona " << kVersion << "\n";
      return 0;
    }
    for (const auto& c : subcommands()) {
      if (args[0] != c.name) continue;
      const ArgParser parser = c.parser();
      const ParsedArgs parsed = parser.parse(std::vector<std::string>(args.begin() + 1, args.end()));
      if (parsed.flag("help")) {
        out << parser.help();
        return 0;
      }
      const Console con{out, err, parsed.flag("quiet"), interactive};
      current_activity() = c.name;
      check_launch(dist::launch_from_environment(), c.name);  // before any rank writes anything
      if (runs_a_model(c.name)) announce_compute(con, compute_options(parsed));
      return c.run(parsed, con);
    }
    usage_fail("unknown command '", args[0], "' (commands: plan, generate, eval, encode, decode, info, convert, synth; see epona --help)");
  } catch (const std::bad_alloc&) {
    return fail_line(err, current_activity() + ": out of memory (an allocation failed; a smaller input or size needs less)");
  } catch (const std::filesystem::filesystem_error& e) {
    return fail_line(err, filesystem_text(e));
  } catch (const std::exception& e) {
    return fail_line(err, e.what());
  }
}

}  // namespace epona::app
