// apps/epona/cmd_synth.hpp — `epona synth`: clips of the procedural driving world
// (include/epona/synth/) for training and evaluation: per clip the history frames and their ego
// motions, the true future frames and motions, the other vehicles' boxes and the drive's
// parameters, as PNG folders or .npy arrays. Layout: docs/synthetic-world.md.
#pragma once

#include <charconv>
#include <cstdio>
#include <filesystem>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "args.hpp"
#include "cmd_common.hpp"
#include "console.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/io/image.hpp"
#include "epona/io/npy.hpp"
#include "epona/synth/scenario.hpp"

namespace epona::app {

inline ArgParser synth_parser() {
  ArgParser p("epona synth", "--out DIR [options]",
              "Generates driving clips from a procedural world (curved multi-lane roads, traffic, trees, poles,\n"
              "buildings, varied light and weather) seen by a forward camera at 5 Hz: per clip F history frames\n"
              "with their ego motions, the true next K frames, the next max(K, 15) motions, the other vehicles'\n"
              "boxes and the drive's parameters. The same seed gives the same bytes; clip k depends only on the\n"
              "seed and k. Layout: docs/synthetic-world.md.");
  p.option("seed", "S", "seed of the run", "0")
      .option("clips", "N", "number of clips (1..100000)", "1")
      .option("frames", "F", "history frames per clip (1..10000)", "10")
      .option("future", "K", "true future frames per clip (0..10000; at least 15 future motions are written)", "15")
      .option("size", "HxW", "frame size, multiples of 32 in 32..4096", "256x512")
      .option("format", "png|npy", "png folders, or frames.npy (uint8) + poses_abs.npy", "png")
      .option("supersample", "N", "samples per pixel side (1..8), box-filtered", "2")
      .option("threads", "N", "rendering threads (the output does not depend on it)", "all cores")
      .flag("explore", "an exploring ego driver: random steering and speed impulses (training data that teaches\n"
                       "a model to follow actions; leave it off for evaluation sets)");
  add_output_options(p, "out/synth");
  p.epilog("examples:\n"
           "  epona synth --seed 1 --clips 100 --frames 10 --out data/synth\n"
           "  epona synth --clips 1000 --frames 20 --future 20 --size 128x256 --format npy --out data/train");
  return p;
}

namespace synth_cmd {

struct Options {
  std::uint64_t seed = 0;
  std::int64_t clips = 1, frames = 10, future = 15, future_poses = 15;
  int height = 256, width = 512, supersample = 2, threads = 1;
  bool npy = false;
  std::optional<synth::Exploration> exploration;
};

inline std::pair<int, int> parse_size(const std::string& text) {
  const auto x = text.find('x');
  auto number = [&](std::string_view v, int& out) {
    const auto [p, ec] = std::from_chars(v.data(), v.data() + v.size(), out);
    return !v.empty() && ec == std::errc() && p == v.data() + v.size();
  };
  int h = 0, w = 0;
  if (x == std::string::npos || !number(std::string_view(text).substr(0, x), h) ||
      !number(std::string_view(text).substr(x + 1), w))
    usage_fail("--size must be HEIGHTxWIDTH (e.g. 256x512), got '", text, "'");
  for (const int v : {h, w})
    if (v < 32 || v > 4096 || v % 32 != 0)
      usage_fail("--size ", text, ": height and width must be multiples of 32 in [32, 4096]");
  return {h, w};
}

inline Options options(const ParsedArgs& a) {
  Options o;
  o.seed = static_cast<std::uint64_t>(a.integer("seed", 0, 0));
  o.clips = a.integer("clips", 1, 1, 100000);
  o.frames = a.integer("frames", 10, 1, 10000);
  o.future = a.integer("future", 15, 0, 10000);
  o.future_poses = std::max<std::int64_t>(o.future, 15);
  std::tie(o.height, o.width) = parse_size(a.text("size", "256x512"));
  o.npy = a.choice("format", {"png", "npy"}, "png") == "npy";
  o.supersample = static_cast<int>(a.integer("supersample", 2, 1, 8));
  if (a.flag("explore")) o.exploration = synth::Exploration{};
  const auto cores = static_cast<std::int64_t>(std::max(1u, std::thread::hardware_concurrency()));
  o.threads = static_cast<int>(a.integer("threads", cores, 1, 1024));
  const double pixels = double(o.height) * o.width * double(o.frames + o.future);
  if (o.npy && pixels * 3 > 16e9)
    usage_fail("--format npy: one clip of ", o.frames + o.future, " frames at ", o.height, "x", o.width,
               " would take more than 16 GB; use fewer frames, a smaller --size or --format png");
  return o;
}

inline std::string num(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.6f", v == 0 ? 0.0 : v);  // no "-0.000000"
  std::string s = buf;
  if (s == "-0.000000") s = "0.000000";
  return s;
}
inline std::string rgb_json(synth::Rgb c) { return "[" + num(c.r) + "," + num(c.g) + "," + num(c.b) + "]"; }

inline std::string camera_json(const synth::Camera& c) {
  return "{\"model\":\"pinhole\",\"height\":" + std::to_string(c.height) + ",\"width\":" + std::to_string(c.width) +
         ",\"hfov_deg\":" + num(c.hfov_deg) + ",\"focal_px\":" + num(c.focal()) +
         ",\"cx\":" + num(0.5 * c.width) + ",\"cy\":" + num(c.horizon * c.height) + ",\"horizon_fraction\":" +
         num(c.horizon) + ",\"mount_height_m\":" + num(c.mount_height) + ",\"pitch_deg\":0}";
}

inline std::string motions_csv(const synth::Scenario& sc, std::int64_t from, std::int64_t count) {
  std::string s = "x,y,yaw\n";
  for (std::int64_t i = from; i < from + count; ++i) {
    const synth::Motion m = sc.motion(i);
    append_shortest(s, static_cast<float>(m.x));
    s += ',';
    append_shortest(s, static_cast<float>(m.y));
    s += ',';
    append_shortest(s, static_cast<float>(m.yaw_deg));
    s += '\n';
  }
  return s;
}

// Every other vehicle within 80 m of the ego, per frame, in the ego frame of the last history frame.
inline std::string boxes_json(const synth::Scenario& sc, std::int64_t history) {
  const synth::Pose2 ref = sc.frames()[static_cast<std::size_t>(history - 1)].ego;
  std::string s = "{\"frame_of\":\"last history frame\",\"ego\":{\"length\":" + num(synth::EgoCar::kLength) +
                  ",\"width\":" + num(synth::EgoCar::kWidth) + "},\"frames\":[";
  for (std::int64_t i = 0; i < sc.size(); ++i) {
    const synth::FrameState& f = sc.frames()[static_cast<std::size_t>(i)];
    s += i ? ",\n[" : "\n[";
    bool first = true;
    for (const synth::VehicleBox& v : f.vehicles) {
      if (std::hypot(v.pose.x - f.ego.x, v.pose.y - f.ego.y) > 80) continue;
      const synth::Motion m = synth::motion_between(ref, v.pose);
      s += (first ? "" : ",") + std::string("{\"x\":") + num(m.x) + ",\"y\":" + num(m.y) + ",\"yaw\":" + num(m.yaw_deg) +
           ",\"length\":" + num(v.length) + ",\"width\":" + num(v.width) + "}";
      first = false;
    }
    s += "]";
  }
  return s + "\n]}\n";
}

inline std::string scene_json(const synth::Scenario& sc, std::uint64_t seed, std::int64_t clip) {
  const synth::DriveParams& p = sc.params();
  double vmin = 1e9, vmax = 0, yaw = 0;
  for (std::int64_t i = 0; i < sc.size(); ++i) {
    vmin = std::min(vmin, sc.frames()[static_cast<std::size_t>(i)].speed);
    vmax = std::max(vmax, sc.frames()[static_cast<std::size_t>(i)].speed);
    yaw += sc.motion(i).yaw_deg;
  }
  const synth::Lighting& L = p.lighting;
  return "{\"seed\":" + std::to_string(seed) + ",\"clip\":" + std::to_string(clip) + ",\"regime\":\"" + p.regime.name +
         "\",\"desired_speed_mps\":[" + num(p.regime.v_min) + "," + num(p.regime.v_max) + "],\"lanes\":" +
         std::to_string(p.layout.lanes) + ",\"oncoming_lane\":" + (p.layout.oncoming ? "true" : "false") +
         ",\"lane_width_m\":" + num(p.layout.lane_width) + ",\"start_lane\":" + std::to_string(p.start_lane) +
         ",\"curve_radius_m\":[" + num(p.road.min_radius) + "," + num(p.road.max_radius) +
         "],\"traffic_spacing_m\":" + num(p.traffic_spacing) + ",\"scenery_per_100m\":{\"trees\":" + num(p.scenery.trees) +
         ",\"poles\":" + num(p.scenery.poles) + ",\"buildings\":" + num(p.scenery.buildings) + "},\"weather\":\"" +
         p.weather + "\",\"sun_elevation_deg\":" + num(p.sun_elevation_deg) + ",\"sun_azimuth_deg\":" +
         num(p.sun_azimuth_deg) + ",\"brightness\":" + num(L.brightness) + ",\"fog_distance_m\":" + num(L.fog_distance) +
         ",\"sky_zenith\":" + rgb_json(L.zenith) + ",\"sky_horizon\":" + rgb_json(L.horizon) + ",\"asphalt\":" +
         rgb_json(p.palette.asphalt) + ",\"grass\":" + rgb_json(p.palette.grass) +
         ",\"recorded\":{\"speed_min_mps\":" + num(vmin) + ",\"speed_max_mps\":" + num(vmax) + ",\"total_yaw_deg\":" +
         num(yaw) + ",\"lane_changes\":" + std::to_string(sc.lane_changes()) + "}" +
         (sc.exploring() ? ",\"exploring_driver\":{\"impulses\":" + std::to_string(sc.impulses()) + "}" : "") + "}\n";
}

inline std::string frame_name(std::int64_t i, std::int64_t count) {
  const int digits = std::max<int>(2, static_cast<int>(std::to_string(std::max<std::int64_t>(count - 1, 0)).size()));
  std::string n = std::to_string(i);
  return "frame_" + std::string(std::max<std::size_t>(n.size(), std::size_t(digits)) - n.size(), '0') + n + ".png";
}

inline void make_dir(const std::filesystem::path& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  EPONA_CHECK(std::filesystem::is_directory(dir, ec), dir.string(), ": cannot create the folder",
              ec ? " (" + ec.message() + ")" : std::string());
}

inline void write_clip(const Options& o, std::int64_t k, const std::filesystem::path& dir) {
  const std::int64_t F = o.frames, K = o.future, P = o.future_poses;
  const synth::Scenario sc(o.seed, static_cast<std::uint64_t>(k), F + P, o.exploration);
  synth::RenderOptions ro;
  ro.camera.height = o.height, ro.camera.width = o.width, ro.supersample = o.supersample, ro.threads = o.threads;
  make_dir(dir);
  if (o.npy) {
    const std::size_t frame_bytes = std::size_t(o.height) * std::size_t(o.width) * 3;
    std::vector<std::byte> frames(frame_bytes * std::size_t(F + K));
    for (std::int64_t i = 0; i < F + K; ++i) {
      const io::Image img = sc.render(i, ro);
      std::memcpy(frames.data() + frame_bytes * std::size_t(i), img.rgb.data(), frame_bytes);
    }
    io::write_npy(dir / "frames.npy", "|u1", {F + K, o.height, o.width, 3}, frames);
    std::vector<double> abs(std::size_t(F + P) * 3);
    for (std::int64_t i = 0; i < F + P; ++i) {
      const synth::Pose2& e = sc.frames()[std::size_t(i)].ego;
      abs[std::size_t(i) * 3] = e.x, abs[std::size_t(i) * 3 + 1] = e.y, abs[std::size_t(i) * 3 + 2] = e.yaw;
    }
    io::write_npy(dir / "poses_abs.npy", "<f8", {F + P, 3}, std::as_bytes(std::span<const double>(abs)));
  } else {
    make_dir(dir / "frames");
    make_dir(dir / "future");
    for (std::int64_t i = 0; i < F; ++i) io::write_png((dir / "frames" / frame_name(i, F)).string(), sc.render(i, ro));
    for (std::int64_t i = 0; i < K; ++i)
      io::write_png((dir / "future" / frame_name(i, K)).string(), sc.render(F + i, ro));
  }
  io::write_atomically(dir / "poses.csv", motions_csv(sc, 0, F));
  io::write_atomically(dir / "future_poses.csv", motions_csv(sc, F, P));
  io::write_atomically(dir / "boxes.json", boxes_json(sc, F));
  io::write_atomically(dir / "scene.json", scene_json(sc, o.seed, k));
}

inline std::string clip_dir_name(std::int64_t k, std::int64_t clips) {
  const int digits = std::max<int>(4, static_cast<int>(std::to_string(clips - 1).size()));
  std::string n = std::to_string(k);
  return "clip_" + std::string(std::max<std::size_t>(n.size(), std::size_t(digits)) - n.size(), '0') + n;
}

}  // namespace synth_cmd

inline int run_synth(const ParsedArgs& a, const Console& con) {
  const synth_cmd::Options o = synth_cmd::options(a);
  const auto dir = output_dir(a, "out/synth");
  synth::Camera cam;
  cam.height = o.height, cam.width = o.width;
  io::write_atomically(dir / "clips.json",
                       "{\"format\":\"epona-synth\",\"version\":1,\"seed\":" + std::to_string(o.seed) +
                           ",\"clips\":" + std::to_string(o.clips) + ",\"frames\":" + std::to_string(o.frames) +
                           ",\"future\":" + std::to_string(o.future) + ",\"future_poses\":" +
                           std::to_string(o.future_poses) + ",\"size\":[" + std::to_string(o.height) + "," +
                           std::to_string(o.width) + "],\"fps\":5,\"image_format\":\"" + (o.npy ? "npy" : "png") +
                           "\",\"supersample\":" + std::to_string(o.supersample) +
                           (o.exploration ? ",\"exploring_driver\":true" : "") + ",\"camera\":" +
                           synth_cmd::camera_json(cam) + "}\n");
  con.note("synth: ", o.clips, " clips of ", o.frames, " + ", o.future, " frames at ", o.height, "x", o.width, ", seed ",
           o.seed, ", ", o.threads, " threads");
  Progress bar(con, "clips", o.clips, "clip");
  for (std::int64_t k = 0; k < o.clips; ++k) {
    synth_cmd::write_clip(o, k, dir / synth_cmd::clip_dir_name(k, o.clips));
    bar.advance();
  }
  con.out << "wrote " << o.clips << " clip" << (o.clips == 1 ? "" : "s") << " to " << dir.string() << " ("
          << (o.npy ? "npy" : "png") << ", " << o.frames << " history + " << o.future << " future frames of "
          << o.height << "x" << o.width << " each)\n";
  return 0;
}

}  // namespace epona::app
