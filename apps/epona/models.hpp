// apps/epona/models.hpp — which model files and configuration a command uses (the bundled
// model when no --weights/--dcae is given; the shipped configuration, WorldModelConfig{} and
// DcaeConfig{}, unless --config names another), the compute options (backend, weight dtype,
// threads), and loading. A binding failure is explained with what the checkpoint's shapes imply.
#pragma once

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <algorithm>
#include <string>
#include <thread>
#include <type_traits>

#include "bundled_model.hpp"
#include "console.hpp"
#include "args.hpp"
#include "inspect.hpp"
#include "epona/core/dtype.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/limits.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/parameter_counts.hpp"
#include "epona/model/world_model.hpp"

namespace epona::app {

// ---- compute options --------------------------------------------------------------------

struct ComputeOptions {
  std::string backend = "cpu";
  bool bf16_weights = false;  // --dtype bfloat16: weights stored in bf16, activations in float32
  int threads = 0;            // 0: all hardware threads
  // Kernels chosen without timing them (on the GPU: cuBLASLt's heuristic first choice for every
  // product), so that every run and every process of a job computes alike: timing picks the
  // fastest candidate, which can differ between processes. EPONA_CUDA_GEMM_TUNE overrides it.
  bool reproducible = true;
  // --tensor-parallel: the VisDiT split over this many shards (GPUs with --backend cuda, threads
  // on the CPU; docs/parallel.md). Every shard runs the rest of the model whole.
  int shards = 1;
  // --shard-sum: how the GPUs of --tensor-parallel add up their partial sums. "peer": our kernel
  // over NVLink/PCIe peer access (cuda/runtime/peer_shard_sum.cuh); "nccl": NCCL's all-reduce;
  // "auto": peer over two GPUs that reach each other's memory (or without NCCL), else NCCL.
  std::string shard_sum = "auto";
};

// --threads beyond a few per hardware thread only slows the work (4096 on 2 cores ran 50x slower).
inline std::int64_t max_threads() {
  const auto hw = static_cast<std::int64_t>(std::max(1u, std::thread::hardware_concurrency()));
  return std::min<std::int64_t>(io::limits::kThreadsCap, io::limits::kThreadsPerCore * hw);
}

// --max-pixels: the limit on one image's (and one resize step's) pixels, raised only on purpose;
// `fallback` is the command's default (io/limits.hpp).
inline std::int64_t max_pixels_option(const ParsedArgs& a, std::int64_t fallback = io::limits::kPixels) {
  return a.integer("max-pixels", fallback, 1024, std::int64_t{1} << 34);
}

// --tensor-parallel's bound: the GPUs of one host.
inline constexpr std::int64_t kMaxShards = 8;

inline void add_compute_options(ArgParser& p) {
  p.option("backend", "NAME", "cpu or cuda", "cpu")
      .option("dtype", "TYPE", "weight precision: float32 (exact) or bfloat16 (half the memory)", "float32")
      .option("threads", "N", "CPU threads; 0 or all: every hardware thread", "all")
      .option("tensor-parallel", "N",
              "split the VisDiT's heads over N shards: N GPUs with --backend cuda, N threads on the CPU",
              "1")
      .option("shard-sum", "HOW",
              "how --tensor-parallel's GPUs add up their parts: peer (our kernel over NVLink), nccl, or auto "
              "(peer over two GPUs that reach each other's memory, nccl over more)",
              "auto");
}

// Refuses a backend this program cannot run, naming why. The epona program gets its CUDA engine
// (apps/epona/cuda_engine.cu, EPONA_APP_CUDA) when CMake finds nvcc.
inline void check_backend(const std::string& backend) {
  if (backend == "cpu") return;
#if defined(EPONA_APP_CUDA)
  return;
#elif defined(EPONA_WITH_CUDA)
  fail("this program was built without its CUDA engine (apps/epona/cuda_engine.cu, compiled into the epona "
       "program when the build has CUDA); use --backend cpu");
#else
  fail("this build has no CUDA backend (configure with -DEPONA_CUDA=ON on a machine with nvcc); use --backend cpu");
#endif
}

inline ComputeOptions compute_options(const ParsedArgs& a) {
  ComputeOptions c;
  c.backend = a.choice("backend", {"cpu", "cuda"}, "cpu");
  const std::string dtype = a.choice("dtype", {"float32", "fp32", "bfloat16", "bf16"}, "float32");
  c.bf16_weights = dtype == "bfloat16" || dtype == "bf16";
  if (a.get("threads") != std::optional<std::string>("all")) c.threads = static_cast<int>(a.integer("threads", 0, 0, max_threads()));
  c.shards = static_cast<int>(a.integer("tensor-parallel", 1, 1, kMaxShards));
  c.shard_sum = a.choice("shard-sum", {"auto", "peer", "nccl"}, "auto");
  EPONA_CHECK(c.shard_sum == "auto" || (c.backend == "cuda" && c.shards > 1), "--shard-sum ", c.shard_sum,
              " applies to --backend cuda with --tensor-parallel 2 or more (the CPU's shards are threads)");
  check_backend(c.backend);
  return c;
}

inline int hardware_threads() { return std::max(1, static_cast<int>(std::thread::hardware_concurrency())); }

// "epona: cpu, float32, 2 threads": what a run computes with, so a log says it without guessing.
inline void announce_compute(const Console& con, const ComputeOptions& c) {
  const std::string split = c.shards > 1 ? ", the VisDiT split over " + std::to_string(c.shards) +
                                               (c.backend == "cuda" ? " GPUs" : " threads' shards")
                                         : "";
  con.note("epona: ", c.backend, ", ", c.bf16_weights ? "bfloat16" : "float32", ", ",
           counted(c.threads > 0 ? c.threads : hardware_threads(), "thread"), split);
}

// ---- which files ------------------------------------------------------------------------

inline void add_model_options(ArgParser& p, bool world, bool dcae) {
  if (world) p.option("weights", "FILE", "world-model checkpoint: official .pkl or .safetensors", "the bundled model");
  if (dcae) p.option("dcae", "FILE", "DC-AE checkpoint: official .pkl (dcae_td_*.pkl) or .safetensors",
                     world ? "the bundled DC-AE, or --weights when it holds the DC-AE too" : "the bundled DC-AE");
  // The default names only the options this command has (encode/decode have no --weights).
  if (world)
    p.option("config", "FILE", "model configuration JSON (configs.json layout, or the world_model_config keys)",
             "the bundled configuration; with --weights/--dcae: the shipped Epona configuration");
  else
    p.option("config", "FILE", "model configuration JSON (configs.json layout; its dcae part is used)",
             "the bundled configuration; with --dcae: the shipped Epona configuration");
}

struct ModelFiles {
  bool demo = false;             // the bundled model (bundled_model())
  std::string world, dcae;       // checkpoint paths (empty when the command does not need one)
  io::ModelConfigs configs;
  std::string config_source;     // named in messages
};

inline void check_file(const std::string& path, const std::string& option) {
  std::error_code ec;
  EPONA_CHECK(std::filesystem::exists(path, ec), option, " ", path, ": no such file");
  EPONA_CHECK(std::filesystem::is_regular_file(path, ec), option, " ", path, ": not a regular file");
}

inline ModelFiles resolve_models(const ParsedArgs& a, bool need_world, bool need_dcae) {
  ModelFiles f;
  f.demo = !a.has("weights") && !a.has("dcae");
  if (f.demo) {
    const std::string dir = demo_model_dir();
    std::error_code ec;
    EPONA_CHECK(std::filesystem::is_directory(dir, ec), "the bundled model is not at ", dir,
                " (set EPONA_MODEL_DIR to the repository's models/small-synthetic, or give --weights/--dcae)");
    if (need_world) f.world = dir + "/weights_world.safetensors";
    if (need_dcae) f.dcae = dir + "/weights_dcae.safetensors";
    f.configs = io::load_configs(a.text("config", dir + "/configs.json"));
    f.config_source = a.text("config", "the bundled configuration " + dir + "/configs.json");
    return f;
  }
  if (need_world) {
    if (!a.has("weights")) usage_fail(a.command(), ": --weights FILE (the world-model checkpoint) is needed with --dcae");
    f.world = *a.get("weights");
    check_file(f.world, "--weights");
  }
  if (need_dcae) {
    if (a.has("dcae")) {
      f.dcae = *a.get("dcae");
      check_file(f.dcae, "--dcae");
    } else if (need_world) {
      f.dcae = f.world;  // a merged checkpoint; load_dcae says so if it holds no DC-AE
    } else {
      usage_fail(a.command(), ": --dcae FILE (the DC-AE checkpoint) is needed with --weights");
    }
  }
  if (a.has("config")) {
    f.configs = io::load_configs(*a.get("config"));
    f.config_source = *a.get("config");
  } else {
    f.configs = io::ModelConfigs{};
    f.config_source = "the shipped Epona configuration";
  }
  return f;
}

// ---- loading ----------------------------------------------------------------------------

inline double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

inline std::string join(const std::vector<std::string>& v, const std::string& sep) {
  std::string s;
  for (std::size_t i = 0; i < v.size(); ++i) s += (i ? sep : "") + v[i];
  return s;
}

// "329 weight problem(s), e.g. 'a' has shape ...; 'b' ...; ..." from the binding's message
// "<file>: 329 weight problem(s): p1; p2; ...": the count and the first `keep` problems.
inline std::string weight_problem_examples(const std::string& what, std::size_t keep) {
  const std::string tag = " weight problem(s): ";
  const auto at = what.find(tag);
  if (at == std::string::npos) return what;
  const auto count_at = what.find_last_not_of("0123456789", at - 1) + 1;
  std::string s = what.substr(count_at, at - count_at) + " weight problem(s), e.g. ";
  std::size_t pos = at + tag.size();
  for (std::size_t shown = 0; shown < keep && pos < what.size(); ++shown) {
    const auto end = std::min(what.find("; ", pos), what.size());
    s += (shown ? "; " : "") + what.substr(pos, end - pos);
    pos = end == what.size() ? end : end + 2;
  }
  return pos < what.size() ? s + "; ..." : s;
}

// Re-throws a binding error with the configuration the checkpoint's shapes imply, when it
// differs from the one used: what is wrong and what to do first, then a few of the keys (the
// binding's list of 20 buried the advice).
[[noreturn]] inline void explain_bind_failure(const Error& e, const std::vector<std::string>& differences,
                                              const ModelFiles& f, const std::string& path) {
  if (differences.empty()) throw e;
  fail(path, ": the checkpoint's shapes differ from ", f.config_source, " in: ", join(differences, "; "),
       "\n  to fix: write the configuration they imply with `epona info ", path,
       " --write-config FILE`, check its assumed values, and pass it with --config FILE",
       "\n  ", weight_problem_examples(e.what(), 3));
}

template <class B, class W>
WorldModel<B, W> load_world(const ModelFiles& f, const ComputeOptions& c, const Console& con,
                            const typename WorldModel<B, W>::VisShard& shard = {}) {
  const auto t0 = std::chrono::steady_clock::now();
  con.note("loading the world model from ", f.world, f.demo ? demo_description() : "");
  const model::FluxDitConfig vis = model::FluxDitConfig::vis(f.configs.world);
  EPONA_CHECK(vis.num_heads % shard.vis.size == 0 && vis.mlp_ratio * vis.hidden_size % shard.vis.size == 0,
              "--tensor-parallel ", shard.vis.size, ": the VisDiT's ", vis.num_heads, " heads and ",
              vis.mlp_ratio * vis.hidden_size, " MLP columns do not split evenly over ", shard.vis.size, " shards");
  const io::TensorMap weights = io::load_weights(f.world);
  try {
    auto wm = WorldModel<B, W>::load(weights, f.configs.world, shard);
    if constexpr (std::is_same_v<B, Cpu>)
      if (c.threads > 0) wm.context().set_threads(c.threads);
    con.note("  ", grouped(std::int64_t(model::world_parameter_counts(f.configs.world).total)), " parameters in ",
             duration_text(seconds_since(t0)));
    return wm;
  } catch (const Error& e) {
    const auto d = detect_configuration(weights, f.configs);
    explain_bind_failure(e, world_differences(d.configs.world, f.configs.world), f, f.world);
  }
}

// The DC-AE's keys of a map (a merged checkpoint also holds module.* world-model keys).
inline io::TensorMap dcae_entries(const io::TensorMap& m) {
  io::TensorMap out(m.source());
  for (const auto& [name, t] : m.entries())
    if (!starts_with(name, "module.")) out.add(name, t);
  return out;
}

template <class B, class T>
Dcae<B, T> load_dcae(const ModelFiles& f, const Console& con) {
  const auto t0 = std::chrono::steady_clock::now();
  con.note("loading the DC-AE from ", f.dcae, f.demo ? demo_description() : "");
  const io::TensorMap all = io::load_weights(f.dcae);
  const io::TensorMap weights = dcae_entries(all);  // views into `all`, which lives until binding is done
  if (weights.size() == 0 || (f.dcae == f.world && !weights.contains("encoder.project_in.conv.conv.weight")))
    fail(f.dcae, ": holds no DC-AE weights (no 'encoder.*' keys", weights.size() == 0 && all.size() ? "; it is a world-model checkpoint" : "",
         "); give the DC-AE checkpoint with --dcae FILE");
  try {
    auto model = Dcae<B, T>::load(weights, f.configs.dcae);
    con.note("  ", grouped(std::int64_t(model::dcae_parameter_counts(f.configs.dcae).total)), " parameters in ",
             duration_text(seconds_since(t0)));
    return model;
  } catch (const Error& e) {
    const auto d = detect_configuration(weights, f.configs);
    explain_bind_failure(e, dcae_differences(d.configs.dcae, f.configs.dcae), f, f.dcae);
  }
}

}  // namespace epona::app
