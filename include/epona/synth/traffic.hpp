// epona/synth/traffic.hpp — the other vehicles: boxes that drive along lanes in road coordinates
// (s, d) with their own desired speeds, follow their leaders with the Intelligent Driver Model
// (Treiber 2000), and now and then change lanes (a smooth lateral move once the target lane has
// room). Vehicles far from the ego stand still until it comes near, so a long drive costs only
// the traffic around the ego.
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "epona/synth/geometry.hpp"
#include "epona/synth/rng.hpp"
#include "epona/synth/road.hpp"

namespace epona::synth {

// A drive's speed regime: desired speeds are drawn in [v_min, v_max] m/s, and held for a while.
struct SpeedRegime {
  const char* name = "urban";
  double v_min = 8, v_max = 14;
  double stop_chance = 0;      // a new desired speed is 0 (stop-and-go)
  double hold_min = 6, hold_max = 15;  // s a desired speed is held
  double draw(Rng& rng) const { return rng.chance(stop_chance) ? 0.0 : rng.uniform(v_min, v_max); }
};

struct IdmParams {
  double accel = 1.5, brake = 2.0;  // m/s^2
  double min_gap = 2.5, headway = 1.3;  // m, s
};

// IDM acceleration at speed v towards desired speed v0 behind a leader `gap` metres ahead (bumper
// to bumper) that is `closing` m/s slower; gap < 0: no leader.
inline double idm_accel(const IdmParams& p, double v, double v0, double gap, double closing) {
  const double free = v0 < 0.5 ? -std::min(p.brake, 2.0 * v) : p.accel * (1 - std::pow(v / v0, 4));
  if (gap < 0) return free;
  const double wanted = p.min_gap + std::max(0.0, v * p.headway + v * closing / (2 * std::sqrt(p.accel * p.brake)));
  const double g = std::max(gap, 0.1);
  return free - p.accel * (wanted / g) * (wanted / g);
}

struct LaneChange {
  double from = 0, to = 0;  // lateral offsets d
  double t = 0, duration = 0;  // in progress while t < duration
  bool active() const { return t < duration; }
  double offset() const { return lerp(from, to, smoothstep(t / duration)); }
  double rate() const {  // dd/dt
    const double u = clampd(t / duration, 0, 1);
    return (to - from) * 6 * u * (1 - u) / duration;
  }
};

struct Vehicle {
  double s = 0, d = 0, v = 0;
  double direction = 1;  // +1 with the ego, -1 oncoming
  int lane = 0;          // target lane (ego direction); -1 oncoming
  LaneChange change;
  double v_desired = 10, hold_left = 10;
  double length = 4.5, width = 1.9, height = 1.5;
  Rgb colour;
  // The pose of the box centre, heading along the motion (including the lateral drift).
  Pose2 pose(const Road& road) const {
    Pose2 p = road.at(s, d, direction);
    if (change.active() && v > 0.5) p.yaw = wrap_angle(p.yaw + direction * std::atan2(change.rate(), v));
    return p;
  }
};

// Something traffic must not drive into (the ego), in road coordinates.
struct Obstacle {
  double s = 0, d = 0, v = 0, length = 4.6;
};

inline Rgb vehicle_colour(Rng& rng) {
  static const Rgb palette[] = {{0.92f, 0.92f, 0.93f}, {0.08f, 0.08f, 0.09f}, {0.55f, 0.57f, 0.6f}, {0.75f, 0.76f, 0.78f},
                                {0.6f, 0.08f, 0.07f},  {0.08f, 0.18f, 0.45f}, {0.12f, 0.3f, 0.15f}, {0.85f, 0.7f, 0.15f},
                                {0.35f, 0.22f, 0.12f}, {0.2f, 0.45f, 0.75f},  {0.9f, 0.45f, 0.1f},  {0.3f, 0.3f, 0.32f}};
  Rgb c = palette[rng.below(12)];
  return scaled(c, rng.uniform(0.9, 1.08));
}

class Traffic {
 public:
  IdmParams idm;
  double change_rate = 1.0 / 40;  // lane changes per vehicle per second

  // Fills lanes with vehicles over [s0, s1], `spacing` metres apart on average.
  void populate(Rng& rng, const Road& road, const RoadLayout& layout, const SpeedRegime& regime, double s0, double s1,
                double spacing, double keep_clear_s, int keep_clear_lane) {
    (void)road;
    for (int lane = -1; lane < layout.lanes; ++lane) {
      if (lane < 0 && !layout.oncoming) continue;
      double s = s0 + rng.uniform(0, spacing);
      while (s < s1) {
        Vehicle v;
        v.direction = lane < 0 ? -1 : 1;
        v.lane = lane;
        v.d = lane < 0 ? layout.oncoming_centre() : layout.lane_centre(lane);
        v.s = s;
        v.length = rng.uniform(4.0, 5.2), v.width = rng.uniform(1.75, 2.0), v.height = rng.uniform(1.4, 1.75);
        if (rng.chance(0.08)) v.length = rng.uniform(7, 11), v.width = 2.45, v.height = rng.uniform(2.8, 3.4);  // van/truck
        v.colour = vehicle_colour(rng);
        v.v_desired = regime.draw(rng) * rng.uniform(0.9, 1.1);
        v.hold_left = rng.uniform(regime.hold_min, regime.hold_max);
        v.v = v.v_desired * rng.uniform(0.7, 1.0);
        const bool blocks_ego = lane == keep_clear_lane && std::abs(s - keep_clear_s) < 12;
        if (!blocks_ego) vehicles.push_back(v);
        s += spacing * rng.uniform(0.5, 1.6) + v.length;
      }
    }
  }

  // One step of dt seconds; only vehicles within [lo, hi] of s move. `ego`: an obstacle for all.
  void step(Rng& rng, const RoadLayout& layout, const SpeedRegime& regime, double dt, double lo, double hi,
            const Obstacle& ego) {
    active_.clear();
    for (std::size_t i = 0; i < vehicles.size(); ++i)
      if (vehicles[i].s >= lo && vehicles[i].s <= hi) active_.push_back(i);
    accel_.assign(active_.size(), 0.0);
    for (std::size_t a = 0; a < active_.size(); ++a) {
      const Vehicle& me = vehicles[active_[a]];
      double gap = -1, closing = 0;
      leader(me, layout, ego, gap, closing);
      accel_[a] = std::clamp(idm_accel(idm, me.v, me.v_desired, gap, closing), -7.0, idm.accel);
    }
    for (std::size_t a = 0; a < active_.size(); ++a) {
      Vehicle& me = vehicles[active_[a]];
      me.v = std::max(0.0, me.v + accel_[a] * dt);
      me.s += me.direction * me.v * dt;
      if (me.change.active()) {
        me.change.t += dt;
        me.d = me.change.active() ? me.change.offset() : me.change.to;
      }
      me.hold_left -= dt;
      if (me.hold_left <= 0) {
        me.v_desired = regime.draw(rng) * rng.uniform(0.9, 1.1);
        me.hold_left = rng.uniform(regime.hold_min, regime.hold_max);
      }
      if (me.direction > 0 && !me.change.active() && layout.lanes > 1 && rng.chance(change_rate * dt) && me.v > 2) {
        const int target = me.lane + (me.lane == 0 ? 1 : me.lane == layout.lanes - 1 ? -1 : (rng.chance(0.5) ? 1 : -1));
        if (lane_free(layout, target, me.s - 12, me.s + 18, &me, ego)) {
          me.change = {me.d, layout.lane_centre(target), 0, rng.uniform(3, 5)};
          me.lane = target;
        }
      }
    }
  }

  // Whether `lane` has no vehicle (or the ego) with its centre in [s0, s1], `self` excepted.
  bool lane_free(const RoadLayout& layout, int lane, double s0, double s1, const Vehicle* self,
                 const Obstacle& ego) const {
    const double c = layout.lane_centre(lane);
    if (std::abs(ego.d - c) < 2.6 && ego.s >= s0 && ego.s <= s1) return false;
    for (const Vehicle& o : vehicles)
      if (&o != self && o.direction > 0 && o.s >= s0 && o.s <= s1 &&
          (std::abs(o.d - c) < 2.6 || (o.change.active() && o.lane == lane)))
        return false;
    return true;
  }

  std::vector<Vehicle> vehicles;

 private:
  // The nearest thing ahead of `me` in its lane (or the lane it moves into): bumper gap, closing speed.
  void leader(const Vehicle& me, const RoadLayout& layout, const Obstacle& ego, double& gap, double& closing) const {
    (void)layout;
    auto consider = [&](double s, double d, double v, double length, double dir) {
      if (dir != me.direction) return;
      const double ahead = (s - me.s) * me.direction;
      const bool same_lane = std::abs(d - me.d) < 2.4 || (me.change.active() && std::abs(d - me.change.to) < 2.4);
      if (ahead <= 0 || !same_lane) return;
      const double g = ahead - 0.5 * (length + me.length);
      if (gap < 0 || g < gap) gap = std::max(g, 0.05), closing = me.v - v;
    };
    consider(ego.s, ego.d, ego.v, ego.length, 1.0);
    for (std::size_t b : active_) {
      const Vehicle& o = vehicles[b];
      if (&o != &me) consider(o.s, o.d, o.v, o.length, o.direction);
    }
  }

  std::vector<std::size_t> active_;
  std::vector<double> accel_;
};

}  // namespace epona::synth
