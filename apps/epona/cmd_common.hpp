// apps/epona/cmd_common.hpp — what plan and generate share: the input-clip options (frames,
// poses, fitting; the bundled demo clip by default), sampling options (steps, seed), the output
// folder, and small writers (a pose CSV that reads back with --poses).
#pragma once

#include <charconv>
#include <filesystem>
#include <string>

#include "args.hpp"
#include "frames.hpp"
#include "models.hpp"
#include "output_paths.hpp"
#include "epona/io/npy.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/domain/poses.hpp"
#include "epona/model/plan_choice.hpp"
#include "epona/model/world_model.hpp"
#include "epona/domain/world_session.hpp"

namespace epona::app {

inline void add_clip_options(ArgParser& p) {
  p.option("frames", "DIR", "folder of the input frames (PNG/JPEG, natural name order; the last F are used)",
           "the bundled model's demo clip")
      .option("poses", "FILE", "one ego motion per frame: .csv/.json (x, y, yaw), the demo's pose.npy+yaw.npy folder, "
              "or absolute 4x4 poses (.npy/.json)", "the demo clip's poses")
      .option("fit", "MODE", "frames not at the model's size: exact (refuse), resize, crop, cover", "exact")
      .option("max-pixels", "N", "refuse input frames (and resize steps) of more pixels", "33554432 (2^25)");
}
// `--sampler fast`: the few-step setting picked by the solver sweep on the bundled model
// (scripts/solver_sweep.sh, docs/solvers.md): of the settings with at most 20 VisDiT evaluations
// a frame, midpoint x 10 alone kept PSNR and planning L2 within 2 % of 100 Euler steps with
// frames closer to them than 50 Euler steps'. Provisional (10 clips): re-measure on your model.
inline constexpr flow::SolverKind kFastSolver = flow::SolverKind::midpoint;
inline constexpr std::int64_t kFastPlanSteps = 10, kFastVideoSteps = 10;

inline void add_sampling_options(ArgParser& p) {
  p.option("sampler", "NAME", "preset: official (Euler, the configuration's steps) or fast (" +
           std::string(flow::solver_name(kFastSolver)) + ", " + std::to_string(kFastPlanSteps) + " planner / " +
           std::to_string(kFastVideoSteps) + " video steps); the options below override it", "official")
      .option("solver", "NAME", "flow solver of both DiTs: " + flow::solver_names() +
              " (heun and midpoint evaluate the DiT twice a step)", "euler")
      .option("steps", "N", "sampling steps of each DiT (1..100000)", "the configuration's num_sampling_steps")
      .option("plan-steps", "N", "the planner's (TrajDiT) steps, overriding --steps", "--steps")
      .option("video-steps", "N", "the video's (VisDiT) steps, overriding --steps", "--steps")
      .option("seed", "N", "noise seed (torch.manual_seed-compatible draws)", "0");
}
// --batch N: up to N clips' work as one batched world-model call (eval, generate --clips). Each
// clip keeps its own seed (per-item noise), so the results are those of --batch 1 up to the
// rounding of the batched matrix products.
inline constexpr std::int64_t kMaxBatch = 64;
inline void add_batch_option(ArgParser& p, const std::string& clips = "clips") {
  p.option("batch", "N", "run up to N " + clips + " together, one world-model call over the batch per step (1.." +
           std::to_string(kMaxBatch) + "); each clip keeps its own seed, so the results are those of --batch 1 "
           "up to float rounding", "1");
}
inline std::int64_t batch_option(const ParsedArgs& a) { return a.integer("batch", 1, 1, kMaxBatch); }
// ", in batches of N clips" for the notes; empty for 1.
inline std::string batch_note(std::int64_t batch) {
  return batch > 1 ? ", in batches of up to " + std::to_string(batch) + " clips" : "";
}
// Multi-hypothesis planning (WorldModel::plan_hypotheses, model/plan_choice.hpp). Without the flags
// the model's recommended rule applies (configs.json "planner"; 1 plan when it has none).
inline void add_hypothesis_options(ArgParser& p) {
  p.option("hypotheses", "K", "plan K trajectories of the scene (hypothesis k draws with seed + k*0x9E3779B9; "
           "the MST runs once) and choose one by --choose (1.." + std::to_string(constants::max_hypotheses) +
           "; 1 = the official single sample)", "the model's configs.json planner.hypotheses, else 1")
      .option("choose", "RULE", "the plan chosen of the hypotheses: medoid (the one nearest all others) or mean "
              "(the waypoint-wise mean)", "the model's planner.choose, else medoid");
}
// The planning rule the command runs, and whether it is the model's recommendation.
struct HypothesisOptions : model::PlanningRule {
  bool from_model = false;  // the model's recommended rule, not the command line's
};
inline HypothesisOptions hypothesis_options(const ParsedArgs& a, const model::PlanningRule& recommended) {
  HypothesisOptions h;
  h.hypotheses = a.integer("hypotheses", recommended.hypotheses, 1, constants::max_hypotheses);
  // choice() accepts only the listed names, so the lookup finds one.
  h.choose = *model::plan_choice_named(a.choice("choose", {"medoid", "mean"}, model::plan_choice_name(recommended.choose)));
  h.from_model = recommended != model::PlanningRule{} && !a.has("hypotheses") && !a.has("choose");
  return h;
}
// "8 hypotheses, the mean chosen (the model's recommended rule)" for the notes.
inline std::string describe(const HypothesisOptions& h) {
  if (h.hypotheses == 1) return "1 plan";
  return std::to_string(h.hypotheses) + " hypotheses, the " + model::plan_choice_name(h.choose) + " chosen" +
         (h.from_model ? " (the model's recommended rule; --hypotheses 1 for the official single sample)" : "");
}

inline void add_output_options(ArgParser& p, const std::string& default_dir) {
  p.option("out", "DIR", "output folder", default_dir, 'o').flag("quiet", "no progress bars or notes on stderr", 'q');
}

struct ClipInputs {
  std::filesystem::path frames, poses;
};

inline ClipInputs clip_inputs(const ParsedArgs& a, const ModelFiles& f) {
  if (!f.demo && !a.has("frames")) usage_fail(a.command(), ": --frames DIR is needed with --weights");
  if (!f.demo && !a.has("poses")) usage_fail(a.command(), ": --poses FILE is needed with --weights");
  ClipInputs in;
  in.frames = a.text("frames", demo_frames_dir());
  in.poses = a.text("poses", a.has("frames") ? "" : demo_poses_file());
  if (in.poses.empty()) usage_fail(a.command(), ": --poses FILE is needed with --frames");
  return in;
}

inline Clip load_clip_for(const ParsedArgs& a, const ModelFiles& f, const Console& con) {
  const ClipInputs in = clip_inputs(a, f);
  const auto& w = f.configs.world;
  const auto policy = size_policy(a.choice("fit", {"exact", "resize", "crop", "cover"}, "exact"));
  Clip clip = load_clip(in.frames, in.poses, w.condition_frames, w.image_h, w.image_w, policy, max_pixels_option(a));
  con.note("input: ", clip.frames.size(), " of ", clip.folder_frames, " frame(s) from ", in.frames.string(),
           " (", w.image_h, "x", w.image_w, "), poses from ", in.poses.string());
  return clip;
}

// The sampling options: the preset, then --solver, --steps, --plan-steps and --video-steps over it.
// Every field is set, so samplers_for(o, anything) gives what the model will run.
inline SampleOptions sample_options(const ParsedArgs& a, const WorldModelConfig& w) {
  SampleOptions o;
  const bool fast = a.choice("sampler", {"official", "fast"}, "official") == "fast";
  o.solver = fast ? kFastSolver : flow::SolverKind::euler;
  if (const auto name = a.get("solver")) {
    try {
      o.solver = flow::parse_solver(*name);
    } catch (const Error& e) {
      usage_fail("--solver: ", e.what());
    }
  }
  const std::int64_t max = constants::max_sampling_steps;
  o.steps = a.integer("steps", w.num_sampling_steps, 1, max);
  o.plan_steps = a.maybe_integer("plan-steps", 1, max);
  o.video_steps = a.maybe_integer("video-steps", 1, max);
  if (fast && !a.has("steps")) {
    if (!o.plan_steps) o.plan_steps = kFastPlanSteps;
    if (!o.video_steps) o.video_steps = kFastVideoSteps;
  }
  if (!o.plan_steps) o.plan_steps = o.steps;
  if (!o.video_steps) o.video_steps = o.steps;
  o.seed = static_cast<std::uint64_t>(a.integer("seed", 0, 0));
  return o;
}

inline DitSamplers samplers_of(const SampleOptions& o) { return samplers_for(o, *o.steps); }

// "planner dpmpp2m x 10 steps (10 DiT evaluations), video euler x 100 steps (100 ...)".
inline std::string describe(const DitSamplers& s, bool plan = true, bool video = true) {
  const auto one = [](const char* what, const flow::SolverSetting& x) {
    return std::string(what) + " " + flow::solver_name(x.kind) + " x " + counted(x.steps, "step") + " (" +
           counted(x.evaluations(), "DiT evaluation") + ")";
  };
  if (plan && video) return one("planner", s.plan) + ", " + one("video", s.video);
  return plan ? one("planner", s.plan) : one("video", s.video);
}

// The --out folder, created and checked for writing before any work.
inline std::filesystem::path output_dir(const ParsedArgs& a, const std::string& fallback) {
  const std::filesystem::path dir = a.text("out", fallback);
  prepare_output_dir(dir, "--out " + dir.string());
  return dir;
}

inline void append_shortest(std::string& s, float v) {
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof buf, v);
  s.append(buf, r.ptr);
}

// x,y,yaw rows (the --poses CSV format), exact float round trip.
inline void write_pose_csv(const std::filesystem::path& path, const io::PoseSequence& p) {
  std::string s = "# motion into each frame: x metres forward, y metres left, yaw degrees (left positive)\nx,y,yaw\n";
  for (std::size_t i = 0; i < p.size(); ++i) {
    append_shortest(s, p.x[i]);
    s += ',';
    append_shortest(s, p.y[i]);
    s += ',';
    append_shortest(s, p.yaw[i]);
    s += '\n';
  }
  io::write_atomically(path, s);
}

inline std::string size_text(const io::Image& img) { return std::to_string(img.height) + "x" + std::to_string(img.width); }

}  // namespace epona::app
