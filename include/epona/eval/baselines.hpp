// epona/eval/baselines.hpp — what a model must beat: constant velocity (the last history motion
// repeated straight ahead, heading fixed), constant turn rate (the last motion, turn included,
// compounded) and, for video, the last history frame repeated.
#pragma once

#include <cstddef>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/eval/ground_truth.hpp"
#include "epona/io/image.hpp"

namespace epona::eval {

// Waypoint n = (n + 1) * (x, y) of the last motion, yaw 0: the speed and direction of travel of
// the last frame step, extrapolated in a straight line.
inline std::vector<Pose2> constant_velocity(const Pose2& last_motion, std::size_t count) {
  std::vector<Pose2> out;
  for (std::size_t n = 0; n < count; ++n)
    out.push_back({double(n + 1) * last_motion.x, double(n + 1) * last_motion.y, 0.0});
  return out;
}

// Waypoint n = the last motion composed n + 1 times (an arc at constant speed and turn rate).
inline std::vector<Pose2> constant_turn(const Pose2& last_motion, std::size_t count) {
  std::vector<Pose2> out;
  Pose2 at;
  for (std::size_t n = 0; n < count; ++n) out.push_back(at = compose(at, last_motion));
  return out;
}

// The video baseline: every future frame predicted as the last history frame.
inline const io::Image& repeat_last_frame(const std::vector<io::Image>& history) {
  EPONA_CHECK(!history.empty(), "repeat_last_frame: no history frames");
  return history.back();
}

}  // namespace epona::eval
