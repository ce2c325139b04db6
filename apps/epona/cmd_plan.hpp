// apps/epona/cmd_plan.hpp — `epona plan`: the last F frames and their ego motions -> the planned
// trajectory (traj_len waypoints of x metres forward, y metres left, yaw degrees, cumulative in
// the ego frame of the last frame) as JSON and CSV, and drawn top-down over the last frame.
#pragma once

#include <cstdio>
#include <filesystem>
#include <string>

#include "args.hpp"
#include "cmd_common.hpp"
#include "console.hpp"
#include "drawing.hpp"
#include "engine.hpp"
#include "frames.hpp"
#include "models.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "epona/io/image.hpp"

namespace epona::app {

inline ArgParser plan_parser() {
  ArgParser p("epona plan", "[options]",
              "Plans the ego trajectory from the last F frames and their ego motions (F = condition_frames,\n"
              "10 for the released model): traj_len waypoints (15 = 3 s at 5 Hz). Writes trajectory.json,\n"
              "trajectory.csv and plan.png (the plan drawn top-down over the last frame) into the output folder.\n"
              "Without --weights it runs the bundled model (models/small-synthetic) on its demo clip.\n"
              "With --hypotheses K it plans K trajectories of the scene, writes the one --choose picks as the plan\n"
              "and all K (with their spread) into trajectory.json, and draws the fan under the plan.");
  add_model_options(p, true, true);
  add_clip_options(p);
  add_sampling_options(p);
  add_hypothesis_options(p);
  add_compute_options(p);
  add_output_options(p, "out/plan");
  p.epilog("examples:\n"
           "  epona plan                                  # the bundled model and clip\n"
           "  epona plan --weights world.pkl --dcae dcae_td_20000.pkl \\\n"
           "             --frames clip/ --poses clip/poses.csv --out out/plan\n"
           "  epona plan --hypotheses 8 --choose mean        # 8 plans, their mean written as the plan");
  return p;
}

inline void print_waypoints(std::ostream& out, const Tensor<float>& traj) {  // (W, 3)
  out << "waypoint      x (m)      y (m)  yaw (deg)\n";
  for (std::int64_t i = 0; i < traj.size(0); ++i) {
    char line[96];
    std::snprintf(line, sizeof line, "%8lld %10.3f %10.3f %10.3f\n", static_cast<long long>(i), double(traj.at(i, 0)),
                  double(traj.at(i, 1)), double(traj.at(i, 2)));
    out << line;
  }
}

// "8 hypotheses, the medoid chosen (hypothesis 3); spread (RMS from their mean): 0.21 m at 1 s, ..."
// at every whole second of the 5 Hz waypoints.
inline void print_spread(std::ostream& out, const model::PlanFan& fan, model::PlanChoice rule) {
  out << fan.hypotheses.size(0) << " hypotheses, the " << model::plan_choice_name(rule) << " chosen";
  if (fan.chosen_index) out << " (hypothesis " << *fan.chosen_index << ")";
  out << "; spread (RMS from their mean):";
  for (std::size_t w = 4; w < fan.spread_m.size(); w += 5) {
    char item[48];
    std::snprintf(item, sizeof item, "%s %.2f m at %zu s", w > 4 ? "," : "", fan.spread_m[w], (w + 1) / 5);
    out << item;
  }
  if (fan.spread_m.size() < 5 && !fan.spread_m.empty()) out << " " << fan.spread_m.back() << " m at the last waypoint";
  out << "\n";
}

inline int run_plan(const ParsedArgs& a, const Console& con) {
  const ComputeOptions compute = compute_options(a);
  const ModelFiles files = resolve_models(a, true, true);
  const SampleOptions sample = sample_options(a, files.configs.world);
  const HypothesisOptions hyp = hypothesis_options(a, files.configs.planner);
  const Clip clip = load_clip_for(a, files, con);
  const auto dir = output_dir(a, "out/plan");
  const auto engine = make_engine(compute);
  engine->load_dcae(files, con);  // only needed to encode the window: freed before the world model loads
  const Tensor<float> latents = encode_frames(*engine, clip.frames, con);
  engine->release_dcae();
  cpu::Context ctx(compute.threads);
  const History history = model::make_window(ctx, latents, clip.poses);
  engine->load_world(files, con);
  con.note("planning: ", describe(samplers_of(sample), true, false), ", seed ", sample.seed,
           hyp.hypotheses > 1 ? ", " + describe(hyp) : std::string());
  const auto t0 = std::chrono::steady_clock::now();
  const Tensor<float> plans = engine->plans(history, hyp.hypotheses, sample);  // (K, traj_len, 3)
  con.note("  planned in ", duration_text(seconds_since(t0)));
  const model::PlanFan fan = model::choose_plan(plans, hyp.choose);
  const Tensor<float>& waypoints = fan.chosen;  // (traj_len, 3)
  if (hyp.hypotheses > 1)
    io::write_trajectory_json(dir / "trajectory.json", waypoints,
                              {plans, model::plan_choice_name(hyp.choose), fan.chosen_index, fan.spread_m});
  else
    io::write_trajectory(dir / "trajectory.json", waypoints);
  io::write_trajectory(dir / "trajectory.csv", waypoints);
  TopDownView view;
  const io::Image picture = draw_plan(clip.frames.back(), waypoints, &view, &plans);
  io::write_png((dir / "plan.png").string(), picture);

  print_waypoints(con.out, waypoints);
  if (hyp.hypotheses > 1) print_spread(con.out, fan, hyp.choose);
  con.out << "wrote " << (dir / "trajectory.json").string() << ", " << (dir / "trajectory.csv").string() << "\n"
          << "wrote " << (dir / "plan.png").string() << " (" << size_text(picture) << ", top-down: "
          << view.pixels_per_metre << " px per metre, ego at the bottom centre)\n";
  return 0;
}

}  // namespace epona::app
