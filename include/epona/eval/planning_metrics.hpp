// epona/eval/planning_metrics.hpp — open-loop planning metrics as nuScenes planners report them
// (ST-P3, UniAD, Epona's Table 2): L2 error of the planned waypoints at 1, 2, 3 s and the
// collision of the ego's box, placed at each waypoint, with the other vehicles' boxes.
//
// Waypoints are at 5 Hz (traj_len = 15 = 3 s), so the waypoint at t seconds is index 5t - 1.
// Two L2 conventions are in use: the error AT time t (UniAD's; our main l2_Ns) and the mean of
// the errors of all waypoints UP TO time t (ST-P3's and VAD's; l2_avg_Ns). Collision uses the
// separating-axis test on oriented boxes, boxes being closed sets: touching counts as a collision.
#pragma once

#include <array>
#include <cmath>
#include <cstddef>
#include <optional>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/eval/ground_truth.hpp"

namespace epona::eval {

inline constexpr std::size_t kWaypointsPerSecond = 5;
inline constexpr std::size_t kPlanSeconds = 3;  // horizons 1, 2, 3 s
inline constexpr std::size_t kPlanWaypoints = kWaypointsPerSecond * kPlanSeconds;

// Index of the waypoint at `seconds` (1 -> 4, 2 -> 9, 3 -> 14).
inline constexpr std::size_t waypoint_at(std::size_t seconds) { return seconds * kWaypointsPerSecond - 1; }

inline double distance(const Pose2& a, const Pose2& b) { return std::hypot(a.x - b.x, a.y - b.y); }

struct L2Errors {
  std::array<double, kPlanSeconds> at{};   // [k]: error of the waypoint at k + 1 seconds
  std::array<double, kPlanSeconds> avg{};  // [k]: mean error of the waypoints up to k + 1 seconds
};

inline L2Errors l2_errors(const std::vector<Pose2>& plan, const std::vector<Pose2>& truth) {
  EPONA_CHECK(plan.size() >= kPlanWaypoints && truth.size() >= kPlanWaypoints, "L2 at 1/2/3 s needs ",
              kPlanWaypoints, " waypoints; the plan has ", plan.size(), ", the ground truth ", truth.size());
  L2Errors e;
  double sum = 0;
  for (std::size_t n = 0; n < kPlanWaypoints; ++n) {
    const double d = distance(plan[n], truth[n]);
    sum += d;
    if ((n + 1) % kWaypointsPerSecond == 0) {
      const std::size_t k = n / kWaypointsPerSecond;
      e.at[k] = d;
      e.avg[k] = sum / double(n + 1);
    }
  }
  return e;
}

// ---- collision ---------------------------------------------------------------------------

// An oriented box in the plane: centre (x fwd, y left; metres), heading (degrees), size (metres).
struct Box2 {
  double x = 0, y = 0, yaw = 0, length = 0, width = 0;
};

struct VehicleSize {
  double length = 0, width = 0;
};

// The ego's box centred on a waypoint, heading along the waypoint's yaw.
inline Box2 box_at(const Pose2& p, const VehicleSize& size) { return {p.x, p.y, p.yaw, size.length, size.width}; }

namespace sat_detail {
inline std::array<std::array<double, 2>, 4> corners(const Box2& b) {
  const double c = std::cos(radians(b.yaw)), s = std::sin(radians(b.yaw));
  const double hl = b.length / 2, hw = b.width / 2;
  std::array<std::array<double, 2>, 4> out;
  const double sign[4][2] = {{1, 1}, {1, -1}, {-1, -1}, {-1, 1}};
  for (int i = 0; i < 4; ++i) {
    const double u = sign[i][0] * hl, v = sign[i][1] * hw;
    out[i] = {b.x + c * u - s * v, b.y + s * u + c * v};
  }
  return out;
}
// True when the boxes' projections on `axis` are disjoint (a positive gap).
inline bool separated_on(const std::array<std::array<double, 2>, 4>& a, const std::array<std::array<double, 2>, 4>& b,
                         double ax, double ay) {
  double amin = INFINITY, amax = -INFINITY, bmin = INFINITY, bmax = -INFINITY;
  for (int i = 0; i < 4; ++i) {
    const double pa = a[i][0] * ax + a[i][1] * ay, pb = b[i][0] * ax + b[i][1] * ay;
    amin = std::min(amin, pa), amax = std::max(amax, pa);
    bmin = std::min(bmin, pb), bmax = std::max(bmax, pb);
  }
  return amax < bmin || bmax < amin;
}
}  // namespace sat_detail

// Separating-axis test: two convex boxes are disjoint iff their projections are disjoint on one
// of the four edge normals. Touching boxes (zero gap) overlap.
inline bool boxes_overlap(const Box2& a, const Box2& b) {
  const auto ca = sat_detail::corners(a), cb = sat_detail::corners(b);
  for (const Box2* box : {&a, &b}) {
    const double c = std::cos(radians(box->yaw)), s = std::sin(radians(box->yaw));
    if (sat_detail::separated_on(ca, cb, c, s) || sat_detail::separated_on(ca, cb, -s, c)) return false;
  }
  return true;
}

// Other vehicles' boxes per future frame (frame n is where waypoint n is), in the ego frame of
// the last history frame, as the plan.
using FutureBoxes = std::vector<std::vector<Box2>>;

// [k]: whether the ego box hits another box at any waypoint up to k + 1 seconds; none when the
// boxes do not reach that far (fewer than 5 (k + 1) future frames).
using Collisions = std::array<std::optional<bool>, kPlanSeconds>;

inline Collisions plan_collisions(const std::vector<Pose2>& plan, const VehicleSize& ego, const FutureBoxes& future) {
  Collisions out;
  bool hit = false;
  const std::size_t n_max = std::min({plan.size(), future.size(), kPlanWaypoints});
  for (std::size_t n = 0; n < n_max; ++n) {
    const Box2 me = box_at(plan[n], ego);
    for (const Box2& other : future[n]) hit = hit || boxes_overlap(me, other);
    if ((n + 1) % kWaypointsPerSecond == 0) out[n / kWaypointsPerSecond] = hit;
  }
  return out;
}

}  // namespace epona::eval
