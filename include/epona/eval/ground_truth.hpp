// epona/eval/ground_truth.hpp — SE(2) poses for the evaluation: the per-frame ego motions of a
// clip (x m forward, y m left, yaw degrees left-positive, each in the ego frame of the frame
// before, domain/poses.hpp) composed into cumulative poses in the ego frame of the last history
// frame — the frame the model's planned waypoints are expressed in (WorldModel::plan).
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <numbers>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/domain/poses.hpp"

namespace epona::eval {

// A pose (or a motion) in the plane: metres forward, metres left, degrees (left turn positive).
struct Pose2 {
  double x = 0, y = 0, yaw = 0;
};

inline double radians(double degrees) { return degrees * std::numbers::pi / 180.0; }

// `a` then `b`, with `b` expressed in the frame `a` leads to. Headings add unwrapped (the
// model's waypoints do not wrap either).
inline Pose2 compose(const Pose2& a, const Pose2& b) {
  const double c = std::cos(radians(a.yaw)), s = std::sin(radians(a.yaw));
  return {a.x + c * b.x - s * b.y, a.y + s * b.x + c * b.y, a.yaw + b.yaw};
}

inline Pose2 motion_at(const io::PoseSequence& m, std::size_t i) { return {m.x[i], m.y[i], m.yaw[i]}; }

// The first `count` motions composed: pose n = motion 0 ∘ ... ∘ motion n, in the frame before
// motion 0 (for a clip's future motions: the last history frame).
inline std::vector<Pose2> cumulative_poses(const io::PoseSequence& motions, std::size_t count) {
  EPONA_CHECK(motions.size() >= count, "cumulative_poses: ", count, " poses asked of ", motions.size(), " motion(s)");
  std::vector<Pose2> out;
  Pose2 at;
  for (std::size_t i = 0; i < count; ++i) out.push_back(at = compose(at, motion_at(motions, i)));
  return out;
}

// A trajectory tensor (W, 3) or (1, W, 3) of x, y, yaw waypoints -> poses.
inline std::vector<Pose2> poses_of(const Tensor<float>& traj) {
  EPONA_CHECK(traj.size(-1) == 3 && traj.numel() % 3 == 0, "a trajectory has (x, y, yaw) rows, got shape ",
              shape_str(traj.shape()));
  std::vector<Pose2> out;
  for (std::int64_t i = 0; i < traj.numel() / 3; ++i)
    out.push_back({traj.data()[3 * i], traj.data()[3 * i + 1], traj.data()[3 * i + 2]});
  return out;
}

}  // namespace epona::eval
