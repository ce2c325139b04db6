// fuzz/fuzz_poses_json.cpp — parse_pose_json (the list, object and {"poses"}/{"absolute"} forms,
// 4x4 matrices through get_rel_pose, float32 range) on arbitrary text.
#include "epona/domain/poses.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(poses_json) {
  return epona_fuzz::run([&] {
    const auto poses = epona::io::parse_pose_json(epona_fuzz::as_text(data, size), "fuzz.json");
    epona_fuzz::require(!poses.empty() && poses.y.size() == poses.size() && poses.yaw.size() == poses.size(),
                        "an accepted pose file has x, y, yaw for each of at least one frame");
  });
}
