// epona/synth/ego_controller.hpp — the ego car's driver: pure-pursuit steering towards a point on
// its lane a speed-dependent distance ahead (Coulter 1992), lane changes at random times in
// either direction when the target lane has room, and IDM car-following of the lead vehicle
// with a desired speed from the drive's regime, capped by the curvature ahead (lateral
// acceleration at most 2.5 m/s^2). The car moves as a kinematic unicycle in world coordinates.
// An exploring driver (training data, `epona synth --explore`) adds steering and speed impulses
// at random moments on top, which the driver then corrects.
#pragma once

#include <algorithm>
#include <cmath>
#include <optional>

#include "epona/synth/geometry.hpp"
#include "epona/synth/rng.hpp"
#include "epona/synth/road.hpp"
#include "epona/synth/traffic.hpp"

namespace epona::synth {

// The exploring driver's impulses. Their onsets cannot be foreseen from the drive so far, so a
// world model trained on such clips must read the next action, not the history, to draw the next
// frame: natural driving alone teaches it to ignore the action (docs/synthetic-world.md).
struct Exploration {
  double mean_interval = 2.0;                    // s between impulse onsets, on average
  double min_yaw_rate = 0.1, max_yaw_rate = 0.9;  // rad/s on top of the steering (0.9: ~10 deg per frame)
  double min_accel = 1.0, max_accel = 3.0;       // m/s^2 on top of the speed control
  double min_duration = 0.2, max_duration = 0.8;  // s
};

inline constexpr double kMaxImpulseYawRate = 0.65;  // rad/s, steering and impulse together

struct Impulse {
  double yaw_rate = 0, accel = 0, left = 0;  // left: seconds still to run
  bool active() const { return left > 0; }
};

struct EgoCar {
  Pose2 pose;
  double v = 0;
  double s = 0, d = 0;  // road coordinates (kept up to date by the controller)
  std::int64_t hint = 0;
  int lane = 0;
  LaneChange change;
  double v_desired = 10, hold_left = 10;
  double next_change_in = 10;  // s until the next lane-change wish
  int lane_changes = 0;
  Impulse impulse;
  double next_impulse_in = 0;
  int impulses = 0;
  static constexpr double kLength = 4.6, kWidth = 1.9;
  Obstacle obstacle() const { return {s, d, v, kLength}; }
};

class EgoController {
 public:
  IdmParams idm{1.6, 2.5, 3.0, 1.4};
  double max_lateral_accel = 2.5;  // m/s^2
  double mean_change_interval = 12;  // s between lane-change wishes
  std::optional<Exploration> exploration;  // set: the exploring driver of training clips

  EgoCar start(Rng& rng, const Road& road, const RoadLayout& layout, const SpeedRegime& regime, double s, int lane) {
    EgoCar e;
    e.lane = lane;
    e.d = layout.lane_centre(lane);
    e.s = s;
    e.pose = road.at(s, e.d);
    e.hint = static_cast<std::int64_t>(s / Road::kStep);
    e.v_desired = regime.draw(rng);
    if (e.v_desired == 0) e.v_desired = regime.v_max * 0.5;  // start moving, so the first motions are real
    e.v = e.v_desired;
    e.hold_left = rng.uniform(regime.hold_min, regime.hold_max);
    e.next_change_in = rng.uniform(2, 2 * mean_change_interval);
    if (exploration) e.next_impulse_in = rng.uniform(0.3, 2 * exploration->mean_interval);
    return e;
  }

  void step(Rng& rng, EgoCar& e, const Road& road, const RoadLayout& layout, const SpeedRegime& regime,
            const Traffic& traffic, double dt) const {
    road.project(e.pose.x, e.pose.y, e.hint, e.s, e.d);
    plan_lane_change(rng, e, layout, traffic, dt);
    if (exploration) plan_impulse(rng, e, dt);
    const double d_ref = e.change.active() ? lerp(e.change.from, e.change.to, smoothstep((e.change.t + 0.6) / e.change.duration))
                                           : layout.lane_centre(e.lane);

    // Pure pursuit: the arc through the look-ahead point.
    const double look = std::clamp(4.0 + 0.9 * e.v, 6.0, 35.0);
    const Pose2 target = road.at(e.s + look, d_ref);
    double lx, ly;
    to_local(e.pose, target.x, target.y, lx, ly);
    const double kappa = std::clamp(2 * ly / std::max(lx * lx + ly * ly, 1.0), -0.2, 0.2);

    // Speed: the regime's wish, the curves ahead, the lead vehicle.
    e.hold_left -= dt;
    if (e.hold_left <= 0) e.v_desired = regime.draw(rng), e.hold_left = rng.uniform(regime.hold_min, regime.hold_max);
    double v0 = e.v_desired;
    for (double ahead = 0; ahead <= 20 + 3 * e.v; ahead += 5)
      v0 = std::min(v0, std::sqrt(max_lateral_accel / std::max(std::abs(road.curvature(e.s + ahead)), 1e-4)));
    double gap = -1, closing = 0;
    lead(e, traffic, gap, closing);
    double a = std::clamp(idm_accel(idm, e.v, v0, gap, closing), -7.0, idm.accel);
    if (e.impulse.active()) a = std::clamp(a + e.impulse.accel, -7.0, idm.accel + e.impulse.accel);
    const double v1 = std::max(0.0, e.v + a * dt);
    const double vm = 0.5 * (e.v + v1);
    double yaw_rate = vm * kappa;
    if (e.impulse.active() && vm > 2) {  // a car at a crawl cannot swerve
      // At most 7.4 degrees a frame: Epona's yaw tokens cover +-8 (models/modules/tokenizer.py).
      yaw_rate = std::clamp(yaw_rate + e.impulse.yaw_rate, -kMaxImpulseYawRate, kMaxImpulseYawRate);
    }
    const double h_mid = e.pose.yaw + 0.5 * yaw_rate * dt;
    e.pose.x += std::cos(h_mid) * vm * dt;
    e.pose.y += std::sin(h_mid) * vm * dt;
    e.pose.yaw = wrap_angle(e.pose.yaw + yaw_rate * dt);
    e.v = v1;
    if (e.change.active()) e.change.t += dt;
  }

  // The nearest vehicle ahead in the ego's lane (or the lane it is moving into).
  static void lead(const EgoCar& e, const Traffic& traffic, double& gap, double& closing) {
    for (const Vehicle& o : traffic.vehicles) {
      if (o.direction < 0) continue;
      const double ahead = o.s - e.s;
      if (ahead <= 0 || ahead > 150) continue;
      const bool same = std::abs(o.d - e.d) < 2.4 || (e.change.active() && std::abs(o.d - e.change.to) < 2.4);
      if (!same) continue;
      const double g = ahead - 0.5 * (o.length + EgoCar::kLength);
      if (gap < 0 || g < gap) gap = std::max(g, 0.05), closing = e.v - o.v;
    }
  }

 private:
  // Starts a steering impulse, a speed impulse or both at random moments; one at a time.
  void plan_impulse(Rng& rng, EgoCar& e, double dt) const {
    const Exploration& x = *exploration;
    if (e.impulse.active()) e.impulse.left -= dt;
    if (!e.impulse.active()) e.impulse = {};
    e.next_impulse_in -= dt;
    if (e.next_impulse_in > 0 || e.impulse.active()) return;
    e.next_impulse_in = rng.uniform(0.3, 1.7) * x.mean_interval;
    const double kind = rng.uniform();
    Impulse im;
    if (kind < 0.7) im.yaw_rate = (rng.chance(0.5) ? 1 : -1) * rng.uniform(x.min_yaw_rate, x.max_yaw_rate);
    if (kind > 0.5) im.accel = (rng.chance(0.5) ? 1 : -1) * rng.uniform(x.min_accel, x.max_accel);
    im.left = rng.uniform(x.min_duration, x.max_duration);
    e.impulse = im;
    ++e.impulses;
  }

  void plan_lane_change(Rng& rng, EgoCar& e, const RoadLayout& layout, const Traffic& traffic, double dt) const {
    if (e.change.active() || layout.lanes < 2) return;
    e.next_change_in -= dt;
    if (e.next_change_in > 0 || e.v < 1.5) return;
    e.next_change_in = rng.uniform(0.3, 1.7) * mean_change_interval;
    const int target = e.lane + (e.lane == 0 ? 1 : e.lane == layout.lanes - 1 ? -1 : (rng.chance(0.5) ? 1 : -1));
    const Obstacle none{-1e9, 0, 0, 0};
    if (!traffic.lane_free(layout, target, e.s - 15, e.s + 20, nullptr, none)) {
      e.next_change_in = rng.uniform(1, 3);  // try again soon
      return;
    }
    e.change = {layout.lane_centre(e.lane), layout.lane_centre(target), 0, std::clamp(rng.uniform(3.5, 5.5), 3.0, 6.0)};
    e.lane = target;
    ++e.lane_changes;
  }
};

}  // namespace epona::synth
