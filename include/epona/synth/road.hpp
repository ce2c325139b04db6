// epona/synth/road.hpp — the road: a centreline parametrised by arc length s, built from a
// curvature profile that is piecewise linear in s (straights, arcs of 40-600 m radius both ways,
// joined by clothoid transitions where the curvature ramps linearly), sampled every metre. Points
// map to road coordinates (s, d: d metres to the left of the centreline) by a local search.
//
// Cross-section (d to the left): an optional oncoming lane on [0, w], the ego direction's lanes
// on [-n w, 0], lane 0 the leftmost (next to the centreline), lane n-1 at the right edge.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/synth/geometry.hpp"
#include "epona/synth/rng.hpp"

namespace epona::synth {

struct RoadLayout {
  int lanes = 2;            // in the ego's direction, 2..4
  bool oncoming = false;    // one lane the other way, left of the centreline
  double lane_width = 3.5;  // m
  double kerb = 0.25;       // m, the raised strip beyond each edge
  double lane_centre(int lane) const { return -(lane + 0.5) * lane_width; }
  double right_edge() const { return -lanes * lane_width; }
  double left_edge() const { return oncoming ? lane_width : 0.0; }
  double oncoming_centre() const { return 0.5 * lane_width; }
  // The lane (0..lanes-1) whose centre is nearest to d.
  int lane_at(double d) const {
    return static_cast<int>(std::clamp(std::floor(-d / lane_width), 0.0, double(lanes - 1)));
  }
};

// How curvy a drive's road is.
struct RoadStyle {
  double min_radius = 40, max_radius = 600;  // m
  double straight_chance = 0.35;             // a segment is a straight
};

class Road {
 public:
  static constexpr double kStep = 1.0;  // m between centreline samples
  static constexpr double kFar = 1e6;   // |d| of a point project() finds no foot point for

  // A road of at least `length` metres from the origin heading along +x.
  static Road generate(Rng& rng, const RoadStyle& style, double length) {
    EPONA_CHECK(length > 0 && length < 1e7, "synth: road length ", length, " out of range");
    // Knots (s, curvature) of the piecewise-linear profile; start with a straight.
    std::vector<double> ks{0.0}, kk{0.0};
    double s = rng.uniform(30, 120);
    ks.push_back(s), kk.push_back(0.0);
    double last_sign = rng.sign();
    while (s < length + 400) {
      double k = 0.0, hold;
      if (rng.chance(style.straight_chance)) {
        hold = rng.uniform(40, 250);
      } else {
        // Log-uniform radius; sign mostly alternating so the road meanders.
        const double r = style.min_radius * std::pow(style.max_radius / style.min_radius, rng.uniform());
        last_sign = rng.chance(0.7) ? -last_sign : last_sign;
        k = last_sign / r;
        hold = std::min(rng.uniform(rad(15), rad(80)) * r, 400.0);  // heading change 15-80 degrees
      }
      const double ramp = rng.uniform(20, 60);
      s += ramp, ks.push_back(s), kk.push_back(k);
      s += hold, ks.push_back(s), kk.push_back(k);
    }
    Road road;
    const auto n = static_cast<std::size_t>(std::ceil((length + 200) / kStep)) + 1;
    road.x_.resize(n), road.y_.resize(n), road.h_.resize(n), road.k_.resize(n), road.cos_.resize(n), road.sin_.resize(n);
    std::size_t knot = 0;
    auto curvature = [&](double at) {
      while (knot + 1 < ks.size() && ks[knot + 1] <= at) ++knot;
      if (knot + 1 >= ks.size()) return kk.back();
      return lerp(kk[knot], kk[knot + 1], (at - ks[knot]) / (ks[knot + 1] - ks[knot]));
    };
    double x = 0, y = 0, h = 0;
    for (std::size_t i = 0; i < n; ++i) {
      const double k0 = curvature(double(i) * kStep);
      road.x_[i] = x, road.y_[i] = y, road.h_[i] = h, road.k_[i] = k0;
      road.cos_[i] = std::cos(h), road.sin_[i] = std::sin(h);
      const double k1 = curvature((double(i) + 1) * kStep);
      const double hm = h + 0.25 * (k0 + k1) * kStep;  // heading at mid-step
      x += std::cos(hm) * kStep, y += std::sin(hm) * kStep;
      h += 0.5 * (k0 + k1) * kStep;
    }
    return road;
  }

  double length() const { return double(x_.size() - 1) * kStep; }
  std::int64_t samples() const { return static_cast<std::int64_t>(x_.size()); }

  // The centreline pose at arc length s (clamped to the road).
  Pose2 centre(double s) const {
    const auto [i, t] = locate(s);
    const double dh = wrap_angle(h_[i + 1] - h_[i]);
    return {lerp(x_[i], x_[i + 1], t), lerp(y_[i], y_[i + 1], t), h_[i] + dh * t};
  }
  double curvature(double s) const {
    const auto [i, t] = locate(s);
    return lerp(k_[i], k_[i + 1], t);
  }
  // The pose of the point (s, d) heading along the road (+1) or against it (-1).
  Pose2 at(double s, double d, double direction = 1.0) const {
    const Pose2 c = centre(s);
    return {c.x - std::sin(c.yaw) * d, c.y + std::cos(c.yaw) * d, direction > 0 ? c.yaw : wrap_angle(c.yaw + kPi)};
  }

  // Road coordinates of the world point (px, py). `hint`: a sample index near the answer, updated
  // (start neighbouring queries from the last answer and each costs a few steps).
  void project(double px, double py, std::int64_t& hint, double& s, double& d) const {
    const std::int64_t last = samples() - 2;
    std::int64_t i = std::clamp<std::int64_t>(hint, 0, last);
    double along = 0;
    for (int iter = 0; iter < 8; ++iter) {
      along = (px - x_[i]) * cos_[i] + (py - y_[i]) * sin_[i];
      const auto step = static_cast<std::int64_t>(std::floor(along / kStep + 0.5));
      if (step == 0) break;
      const std::int64_t next = std::clamp<std::int64_t>(i + std::clamp<std::int64_t>(step, -64, 64), 0, last);
      if (next == i) break;
      i = next;
    }
    const double c = cos_[i], sn = sin_[i];
    along = (px - x_[i]) * c + (py - y_[i]) * sn;
    d = -(px - x_[i]) * sn + (py - y_[i]) * c;
    s = double(i) * kStep + along;
    hint = i;
    if (std::abs(along) > 2 * kStep && i > 0 && i < last) d = d >= 0 ? kFar : -kFar;  // no nearby foot point
  }

  // The smallest distance from (px, py) to the centreline samples in [s0, s1].
  double distance_to(double px, double py, double s0, double s1) const {
    const auto lo = static_cast<std::int64_t>(std::max(0.0, std::floor(s0 / kStep)));
    const auto hi = std::min(samples() - 1, static_cast<std::int64_t>(std::ceil(s1 / kStep)));
    double best = 1e300;
    for (std::int64_t i = lo; i <= hi; ++i) best = std::min(best, std::hypot(px - x_[i], py - y_[i]));
    return best;
  }

 private:
  std::pair<std::size_t, double> locate(double s) const {
    const double u = clampd(s / kStep, 0.0, double(x_.size() - 1) - 1e-9);
    const auto i = static_cast<std::size_t>(u);
    return {i, u - double(i)};
  }

  std::vector<double> x_, y_, h_, k_, cos_, sin_;
};

}  // namespace epona::synth
