// epona/synth/scenario.hpp — one drive of the synthetic world: draws the drive's parameters
// (speed regime, lanes, road curviness, traffic density, scenery, lighting, colours) from the
// clip's own random stream, simulates the ego and the traffic at 20 Hz after a 3 s warm-up,
// and records the state every 0.2 s (Epona's 5 Hz): ego pose, speed, lane, nearby vehicles.
// Frames are rendered on demand from the records. Clip k of seed S depends on (S, k) only.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "epona/synth/ego_controller.hpp"
#include "epona/synth/geometry.hpp"
#include "epona/synth/render.hpp"
#include "epona/synth/rng.hpp"
#include "epona/synth/road.hpp"
#include "epona/synth/scenery.hpp"
#include "epona/synth/traffic.hpp"

namespace epona::synth {

inline constexpr double kFps = 5;           // Epona's frame rate
inline constexpr int kStepsPerFrame = 4;    // 20 Hz simulation
inline constexpr int kWarmupFrames = 15;    // 3 s before the first recorded frame

struct DriveParams {
  int regime_index = 1;  // 0 stop-and-go, 1 urban, 2 highway
  SpeedRegime regime;
  RoadLayout layout;
  RoadStyle road;
  SceneryStyle scenery;
  Lighting lighting;
  Palette palette;
  double traffic_spacing = 40;  // m between vehicles in a lane, on average
  int start_lane = 0;
  double sun_elevation_deg = 40, sun_azimuth_deg = 0;
  const char* weather = "clear";
};

inline SpeedRegime regime_of(int index) {
  if (index == 0) return {"stop-and-go", 2, 8, 0.35, 3, 8};
  if (index == 2) return {"highway", 20, 33, 0, 8, 20};
  return {"urban", 8, 14, 0, 6, 15};
}

inline DriveParams draw_params(Rng& rng) {
  DriveParams p;
  p.regime_index = static_cast<int>(rng.below(3));
  p.regime = regime_of(p.regime_index);
  const bool highway = p.regime_index == 2;
  p.layout.lanes = static_cast<int>(highway ? rng.range(2, 4) : rng.range(2, 3));
  p.layout.oncoming = rng.chance(highway ? 0.2 : 0.5);
  p.road = highway ? RoadStyle{200, 600, 0.4} : RoadStyle{40, 400, 0.35};
  p.scenery = highway ? SceneryStyle{rng.uniform(5, 12), rng.uniform(0.5, 2), rng.uniform(0, 0.8), 6}
                      : SceneryStyle{rng.uniform(2, 6), rng.uniform(2, 5), rng.uniform(2, 6), 3};
  p.traffic_spacing = p.regime_index == 0 ? rng.uniform(6, 14) : highway ? rng.uniform(45, 110) : rng.uniform(20, 50);
  p.start_lane = static_cast<int>(rng.below(p.layout.lanes));

  // Lighting: the sun, the sky, haze; sometimes overcast or foggy.
  Lighting& L = p.lighting;
  p.sun_elevation_deg = rng.uniform(8, 65);
  p.sun_azimuth_deg = rng.uniform(-180, 180);
  const double el = rad(p.sun_elevation_deg), az = rad(p.sun_azimuth_deg);
  L.sun_dir = {std::cos(el) * std::cos(az), std::cos(el) * std::sin(az), std::sin(el)};
  const double low = clampd(1 - p.sun_elevation_deg / 30, 0, 1);
  L.sun = mix(Rgb{1, 0.97f, 0.92f}, Rgb{1, 0.72f, 0.45f}, low);
  L.brightness = rng.uniform(0.8, 1.15);
  const double weather = rng.uniform();
  if (weather < 0.2) {
    p.weather = "overcast";
    L.zenith = scaled(Rgb{0.58f, 0.61f, 0.66f}, rng.uniform(0.85, 1.1));
    L.horizon = scaled(Rgb{0.76f, 0.78f, 0.8f}, rng.uniform(0.9, 1.05));
    L.sun = {1, 1, 1};
    L.ambient = 0.75, L.diffuse = 0.15, L.glow = 0.05;
    L.fog_distance = rng.uniform(180, 400);
  } else if (weather < 0.3) {
    p.weather = "fog";
    L.zenith = scaled(Rgb{0.7f, 0.72f, 0.74f}, rng.uniform(0.9, 1.05));
    L.horizon = L.zenith;
    L.sun = {1, 1, 1};
    L.ambient = 0.8, L.diffuse = 0.1, L.glow = 0.02;
    L.fog_distance = rng.uniform(50, 110);
  } else {
    L.zenith = {float(rng.uniform(0.18, 0.35)), float(rng.uniform(0.38, 0.55)), float(rng.uniform(0.75, 0.95))};
    L.horizon = mix(Rgb{float(rng.uniform(0.72, 0.86)), float(rng.uniform(0.8, 0.88)), float(rng.uniform(0.86, 0.95))},
                    Rgb{0.95f, 0.75f, 0.55f}, 0.5 * low);
    L.ambient = rng.uniform(0.4, 0.55), L.diffuse = rng.uniform(0.5, 0.7);
    L.fog_distance = rng.uniform(300, 1000);
  }
  // Surfaces.
  Palette& P = p.palette;
  const double a = rng.uniform(0.24, 0.42);
  P.asphalt = {float(a), float(a * rng.uniform(0.98, 1.02)), float(a * rng.uniform(1.0, 1.06))};
  P.kerb = scaled(Rgb{0.62f, 0.62f, 0.6f}, rng.uniform(0.85, 1.1));
  if (highway || rng.chance(0.3)) {
    P.shoulder = scaled(Rgb{0.47f, 0.43f, 0.37f}, rng.uniform(0.8, 1.1)), P.shoulder_width = rng.uniform(0.8, 2.5);
  } else {
    P.shoulder = scaled(Rgb{0.6f, 0.59f, 0.57f}, rng.uniform(0.85, 1.1)), P.shoulder_width = rng.uniform(2, 4);  // pavement
  }
  if (rng.chance(0.25)) {  // dry grass
    P.grass = {0.5f, 0.46f, 0.26f}, P.grass2 = {0.42f, 0.4f, 0.22f};
  } else {
    P.grass = {float(rng.uniform(0.18, 0.3)), float(rng.uniform(0.36, 0.5)), float(rng.uniform(0.1, 0.2))};
    P.grass2 = {float(rng.uniform(0.3, 0.42)), float(rng.uniform(0.42, 0.5)), float(rng.uniform(0.15, 0.25))};
  }
  P.dash = rng.uniform(2.5, 4.5), P.gap = rng.uniform(5, 10);
  return p;
}

// A vehicle as recorded at one frame (world coordinates).
struct VehicleBox {
  Pose2 pose;
  double length = 4.5, width = 1.9, height = 1.5;
  Rgb colour;
};

struct FrameState {
  Pose2 ego;
  double speed = 0, s = 0, d = 0;
  int lane = 0;
  std::vector<VehicleBox> vehicles;  // within 400 m of the ego along the road
};

class Scenario {
 public:
  // Simulates `frames` recorded frames of clip `clip` of run `seed`; with `exploration`, driven by
  // the exploring driver (ego_controller.hpp), otherwise the same drive as ever.
  Scenario(std::uint64_t seed, std::uint64_t clip, std::int64_t frames,
           std::optional<Exploration> exploration = std::nullopt)
      : seed_(seed), clip_(clip) {
    EPONA_CHECK(frames >= 1 && frames <= 1000000, "synth: frame count ", frames, " out of range");
    Rng rng = Rng::for_clip(seed, clip);
    params_ = draw_params(rng);
    Rng road_rng = rng.split(), scenery_rng = rng.split(), traffic_rng = rng.split(), ego_rng = rng.split();
    const double start_s = 150;
    const double length = start_s + double(frames + kWarmupFrames) / kFps * params_.regime.v_max * 1.15 + 600;
    road_ = Road::generate(road_rng, params_.road, length);
    props_ = place_scenery(scenery_rng, road_, params_.layout, params_.scenery, 0, road_.length());
    EgoController controller;
    controller.exploration = exploration;
    EgoCar ego = controller.start(ego_rng, road_, params_.layout, params_.regime, start_s, params_.start_lane);
    traffic_.populate(traffic_rng, road_, params_.layout, params_.regime, 20, road_.length() - 50,
                      params_.traffic_spacing, start_s, params_.start_lane);
    const double dt = 1.0 / (kFps * kStepsPerFrame);
    for (std::int64_t f = 0; f < frames + kWarmupFrames; ++f) {
      for (int k = 0; k < kStepsPerFrame; ++k) {
        controller.step(ego_rng, ego, road_, params_.layout, params_.regime, traffic_, dt);
        traffic_.step(traffic_rng, params_.layout, params_.regime, dt, ego.s - 300, ego.s + 600, ego.obstacle());
      }
      if (f == kWarmupFrames - 1) before_ = ego.pose;
      if (f >= kWarmupFrames) frames_.push_back(record(ego));
    }
    ego_lane_changes_ = ego.lane_changes;
    exploring_ = exploration.has_value();
    impulses_ = ego.impulses;
  }

  const DriveParams& params() const { return params_; }
  const Road& road() const { return road_; }
  const std::vector<FrameState>& frames() const { return frames_; }
  std::int64_t size() const { return static_cast<std::int64_t>(frames_.size()); }
  // Epona's motion into frame i (from frame i-1; frame -1 is the last warm-up frame).
  Motion motion(std::int64_t i) const { return motion_between(i == 0 ? before_ : frames_[i - 1].ego, frames_[i].ego); }
  bool exploring() const { return exploring_; }
  int impulses() const { return impulses_; }  // the exploring driver's impulses, warm-up included
  // Lane changes begun during the recorded frames.
  int lane_changes() const {
    int n = 0;
    for (std::size_t i = 1; i < frames_.size(); ++i) n += frames_[i].lane != frames_[i - 1].lane;
    return n;
  }

  // The triangles of everything standing near frame i's ego.
  std::vector<Triangle> triangles(std::int64_t i) const {
    const FrameState& fs = frames_[static_cast<std::size_t>(i)];
    Mesh mesh(params_.lighting);
    const Rgb shadow = scaled(params_.palette.asphalt, 0.45);
    for (const VehicleBox& v : fs.vehicles) mesh.vehicle(v.pose, v.length, v.width, v.height, v.colour, shadow);
    auto first = std::lower_bound(props_.begin(), props_.end(), fs.s - 40,
                                  [](const Prop& p, double s) { return p.s < s; });
    for (auto it = first; it != props_.end() && it->s < fs.s + 500; ++it) mesh.prop(*it);
    return std::move(mesh.triangles);
  }

  io::Image render(std::int64_t i, const RenderOptions& opt) const { return render(i, opt, frames_[static_cast<std::size_t>(i)].ego); }

  // Frame i's world (its vehicles, the scenery near it) seen from `ego` instead of the recorded
  // pose: the view had the ego stood or looked elsewhere at that moment (a turned camera, a step
  // ahead). Used to check measurements against what the camera would really show.
  io::Image render(std::int64_t i, const RenderOptions& opt, const Pose2& ego) const {
    const Renderer r(road_, params_.layout, params_.palette, params_.lighting, opt);
    return r.render(ego, triangles(i));
  }

 private:
  FrameState record(const EgoCar& ego) const {
    FrameState fs;
    fs.ego = ego.pose, fs.speed = ego.v, fs.s = ego.s, fs.d = ego.d, fs.lane = ego.lane;
    for (const Vehicle& v : traffic_.vehicles)
      if (v.s > ego.s - 60 && v.s < ego.s + 400) fs.vehicles.push_back({v.pose(road_), v.length, v.width, v.height, v.colour});
    return fs;
  }

  std::uint64_t seed_, clip_;
  DriveParams params_;
  Road road_;
  std::vector<Prop> props_;
  Traffic traffic_;
  Pose2 before_;
  std::vector<FrameState> frames_;
  int ego_lane_changes_ = 0;
  bool exploring_ = false;
  int impulses_ = 0;
};

}  // namespace epona::synth
