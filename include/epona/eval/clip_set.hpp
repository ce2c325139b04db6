// epona/eval/clip_set.hpp — an evaluation clip set as `epona synth` writes it: DIR/clip_*/ with
// frames/ (history frames), poses.csv (one motion per history frame), future/ (the true next
// frames), future_poses.csv (the motions into them) and boxes.json (ego size and the other
// vehicles' boxes per frame, in the ego frame of the last history frame). Only frames/ and
// poses.csv are required; a clip lacking the rest is skipped by the metrics that need it.
// Every error names the clip and the file.
#pragma once

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "epona/core/error.hpp"
#include "epona/domain/poses.hpp"
#include "epona/eval/planning_metrics.hpp"
#include "epona/io/image_folder.hpp"
#include "epona/io/json_reader.hpp"
#include "epona/io/npy.hpp"

namespace epona::eval {

// Ego size and other vehicles' boxes: one list per frame, the history frames then the future.
struct SceneBoxes {
  VehicleSize ego;
  std::vector<std::vector<Box2>> frames;
};

struct EvalClip {
  std::string name;  // the folder's name
  std::filesystem::path dir;
  std::vector<std::filesystem::path> frames;         // history frames, natural name order
  io::PoseSequence poses;                            // motion into each history frame
  std::vector<std::filesystem::path> future_frames;  // empty without future/
  std::optional<io::PoseSequence> future_motions;    // motion into each future frame
  std::optional<SceneBoxes> boxes;

  // Other vehicles' boxes at each future frame (none without boxes.json).
  FutureBoxes future_boxes() const {
    if (!boxes) return {};
    return FutureBoxes(boxes->frames.begin() + static_cast<std::ptrdiff_t>(frames.size()), boxes->frames.end());
  }
};

namespace clip_detail {

inline double finite_number(const nlohmann::json& j, const char* key, const std::string& where) {
  EPONA_CHECK(j.is_object() && j.contains(key), where, ": missing \"", key, "\"");
  const auto& v = j[key];
  EPONA_CHECK(v.is_number(), where, ": \"", key, "\" must be a number, got ", io::json_brief(v));
  const double d = v.get<double>();
  EPONA_CHECK(std::isfinite(d), where, ": \"", key, "\" is not finite");
  return d;
}

inline double positive_size(const nlohmann::json& j, const char* key, const std::string& where) {
  const double d = finite_number(j, key, where);
  EPONA_CHECK(d > 0, where, ": \"", key, "\" must be positive, got ", d);
  return d;
}

inline bool is_dir(const std::filesystem::path& p) {
  std::error_code ec;
  return std::filesystem::is_directory(p, ec);
}
inline bool is_file(const std::filesystem::path& p) {
  std::error_code ec;
  return std::filesystem::is_regular_file(p, ec);
}

}  // namespace clip_detail

// boxes.json: {"ego": {"length", "width"}, "frames": [[{"x", "y", "yaw", "length", "width"}, ...], ...]}.
inline SceneBoxes read_boxes(const std::filesystem::path& file) {
  using namespace clip_detail;
  const std::string src = file.string();
  const auto bytes = io::read_whole_file(file);
  nlohmann::json j = io::parse_json(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()), src);
  EPONA_CHECK(j.is_object() && j.contains("ego") && j.contains("frames"), src,
              ": expected {\"ego\": {\"length\", \"width\"}, \"frames\": [[boxes of frame 0], ...]}");
  SceneBoxes s;
  s.ego = {positive_size(j["ego"], "length", src + ": ego"), positive_size(j["ego"], "width", src + ": ego")};
  EPONA_CHECK(j["frames"].is_array(), src, ": \"frames\" must be a list (one list of boxes per frame)");
  for (std::size_t f = 0; f < j["frames"].size(); ++f) {
    const auto& list = j["frames"][f];
    const std::string where = epona::detail::concat(src, ": frame ", f);
    EPONA_CHECK(list.is_array(), where, ": expected a list of boxes, got ", list.type_name());
    std::vector<Box2> boxes;
    for (std::size_t b = 0; b < list.size(); ++b) {
      const std::string at = epona::detail::concat(where, ", box ", b);
      boxes.push_back({finite_number(list[b], "x", at), finite_number(list[b], "y", at), finite_number(list[b], "yaw", at),
                       positive_size(list[b], "length", at), positive_size(list[b], "width", at)});
    }
    s.frames.push_back(std::move(boxes));
  }
  return s;
}

// The clip folders of a set: every subfolder of `root` holding frames/, in natural name order; or
// `root` alone when it holds frames/ itself (one clip, e.g. a model's demo clip).
inline std::vector<std::filesystem::path> find_clip_folders(const std::filesystem::path& root) {
  std::error_code ec;
  EPONA_CHECK(std::filesystem::exists(root, ec), "--clips ", root.string(), ": no such folder");
  EPONA_CHECK(std::filesystem::is_directory(root, ec), "--clips ", root.string(), ": not a folder");
  if (clip_detail::is_dir(root / "frames")) return {root};
  std::vector<std::filesystem::path> clips;
  for (const auto& e : std::filesystem::directory_iterator(root, ec))
    if (clip_detail::is_dir(e.path()) && clip_detail::is_dir(e.path() / "frames")) clips.push_back(e.path());
  EPONA_CHECK(!ec, "--clips ", root.string(), ": cannot list the folder: ", ec.message());
  EPONA_CHECK(!clips.empty(), "--clips ", root.string(), ": no clips (subfolders holding frames/) in the folder");
  io::sort_natural(clips);
  return clips;
}

// Reads a clip's file lists, motions and boxes (not its images) and checks they agree.
inline EvalClip read_clip(const std::filesystem::path& dir) {
  using namespace clip_detail;
  EvalClip c;
  c.dir = dir;
  c.name = dir.filename().string();
  const std::string what = "clip " + c.name + ":";
  c.frames = io::image_files(dir / "frames", what);
  EPONA_CHECK(!c.frames.empty(), what, " ", (dir / "frames").string(), ": no .png/.jpg/.jpeg frames in the folder");
  const auto poses = dir / "poses.csv";
  EPONA_CHECK(is_file(poses), what, " ", poses.string(), ": no such file (one x,y,yaw motion per history frame)");
  c.poses = io::load_poses(poses);
  EPONA_CHECK(c.poses.size() == c.frames.size(), what, " ", poses.string(), " holds ", c.poses.size(),
              " pose(s) for the ", c.frames.size(), " frame(s) in ", (dir / "frames").string());
  if (is_dir(dir / "future")) c.future_frames = io::image_files(dir / "future", what);
  if (is_file(dir / "future_poses.csv")) c.future_motions = io::load_poses(dir / "future_poses.csv");
  if (is_file(dir / "boxes.json")) {
    c.boxes = read_boxes(dir / "boxes.json");
    EPONA_CHECK(c.boxes->frames.size() >= c.frames.size(), what, " ", (dir / "boxes.json").string(), " holds ",
                c.boxes->frames.size(), " frame(s) of boxes; the clip has ", c.frames.size(),
                " history frame(s), then the future ones");
  }
  return c;
}

// What the evaluation needs of each clip that has the parts for it.
struct ClipNeeds {
  std::size_t window = 1;          // history frames (the model's condition_frames)
  std::size_t plan_waypoints = 0;  // future motions, when future_poses.csv is there (0: no planning)
  std::size_t video_frames = 0;    // future frames and motions, when future/ is there (0: no video)
};

inline void check_clip(const EvalClip& c, const ClipNeeds& need) {
  const std::string what = "clip " + c.name + ":";
  EPONA_CHECK(c.frames.size() >= need.window, what, " ", (c.dir / "frames").string(), " holds ", c.frames.size(),
              " frame(s); the model's window needs ", need.window);
  const std::size_t motions = std::max(need.plan_waypoints, c.future_frames.empty() ? 0 : need.video_frames);
  if (c.future_motions)
    EPONA_CHECK(c.future_motions->size() >= motions, what, " ", (c.dir / "future_poses.csv").string(), " holds ",
                c.future_motions->size(), " motion(s); ", motions, " are needed (",
                need.plan_waypoints >= motions ? "the 3 s plan" : "one per video horizon", ")");
  if (need.video_frames > 0 && !c.future_frames.empty()) {
    EPONA_CHECK(c.future_frames.size() >= need.video_frames, what, " ", (c.dir / "future").string(), " holds ",
                c.future_frames.size(), " frame(s); --horizon asks for ", need.video_frames);
    EPONA_CHECK(c.future_motions.has_value(), what, " ", (c.dir / "future_poses.csv").string(),
                ": no such file (the video rollout follows the true motions into the future frames)");
  }
}

}  // namespace epona::eval
