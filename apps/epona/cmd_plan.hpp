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
#include "epona/io/image.hpp"
#include "epona/io/trajectory_io.hpp"

namespace epona::app {

inline ArgParser plan_parser() {
  ArgParser p("epona plan", "[options]",
              "Plans the ego trajectory from the last F frames and their ego motions (F = condition_frames,\n"
              "10 for the released model): traj_len waypoints (15 = 3 s at 5 Hz). Writes trajectory.json,\n"
              "trajectory.csv and plan.png (the plan drawn top-down over the last frame) into the output folder.\n"
              "Without --weights it runs the bundled model (models/small-synthetic) on its demo clip.");
  add_model_options(p, true, true);
  add_clip_options(p);
  add_sampling_options(p);
  add_compute_options(p);
  add_output_options(p, "out/plan");
  p.epilog("examples:\n"
           "  epona plan                                  # the bundled model and clip\n"
           "  epona plan --weights world.pkl --dcae dcae_td_20000.pkl \\\n"
           "             --frames clip/ --poses clip/poses.csv --out out/plan");
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

inline int run_plan(const ParsedArgs& a, const Console& con) {
  const ComputeOptions compute = compute_options(a);
  const ModelFiles files = resolve_models(a, true, true);
  const SampleOptions sample = sample_options(a, files.configs.world);
  const Clip clip = load_clip_for(a, files, con);
  const auto dir = output_dir(a, "out/plan");
  const auto engine = make_engine(compute);
  engine->load_dcae(files, con);  // only needed to encode the window: freed before the world model loads
  const Tensor<float> latents = encode_frames(*engine, clip.frames, con);
  engine->release_dcae();
  cpu::Context ctx(compute.threads);
  const History history = make_history(ctx, latents, clip.poses);
  engine->load_world(files, con);
  con.note("planning: ", describe(samplers_of(sample), true, false), ", seed ", sample.seed);
  const auto t0 = std::chrono::steady_clock::now();
  const Tensor<float> plan = engine->plan(history, sample);  // (1, traj_len, 3)
  con.note("  planned in ", seconds_since(t0), " s");

  const Tensor<float> waypoints = plan[0];  // (traj_len, 3)
  io::write_trajectory(dir / "trajectory.json", plan);
  io::write_trajectory(dir / "trajectory.csv", plan);
  TopDownView view;
  const io::Image picture = draw_plan(clip.frames.back(), waypoints, &view);
  io::write_png((dir / "plan.png").string(), picture);

  print_waypoints(con.out, waypoints);
  con.out << "wrote " << (dir / "trajectory.json").string() << ", " << (dir / "trajectory.csv").string() << "\n"
          << "wrote " << (dir / "plan.png").string() << " (" << size_text(picture) << ", top-down: "
          << view.pixels_per_metre << " px per metre, ego at the bottom centre)\n";
  return 0;
}

}  // namespace epona::app
