// fuzz/fuzz_poses_csv.cpp — parse_pose_csv (line walker, comments, BOM, header detection and
// column order, number parsing, float32 range) on arbitrary text.
#include "epona/domain/poses.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(poses_csv) {
  return epona_fuzz::run([&] {
    const auto poses = epona::io::parse_pose_csv(epona_fuzz::as_text(data, size), "fuzz.csv");
    epona_fuzz::require(!poses.empty() && poses.y.size() == poses.size() && poses.yaw.size() == poses.size(),
                        "an accepted pose file has x, y, yaw for each of at least one frame");
  });
}
