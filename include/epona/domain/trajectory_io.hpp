// epona/domain/trajectory_io.hpp — planned trajectories to and from files: TrajDiT's denormalised
// output (S steps x W = 15 waypoints x [x m, y m, yaw deg], what test_free.py saves as
// pred_traj.pt) as CSV, JSON or .npy (written under a temp name, then renamed), read back
// exactly (shortest round-trip decimals), and turned into per-step actions for a replay.
//
// Waypoint n of step s is the ego pose n+1 frames after that step's current frame, in the ego
// frame of the current frame (cumulative, not frame-to-frame): x forward, y left, yaw positive =
// turning left (docs/api.md). At 5 Hz the 15 waypoints span 3 s.
#pragma once

#include <charconv>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/domain/poses.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/io/npy.hpp"

namespace epona::io {

namespace traj_detail {

inline constexpr std::string_view kFormat = "epona-trajectory";
inline constexpr std::string_view kCsvHeader = "step,waypoint,x,y,yaw";

// Shortest decimal that reads back as the same float ("-0.0" for negative zero: JSON readers
// take "-0" for the integer 0).
inline void append_float(std::string& out, float v) {
  if (v == 0 && std::signbit(v)) return void(out += "-0.0");
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof buf, v);
  out.append(buf, r.ptr);
}

// (W, 3) or (S, W, 3) -> (S, W, 3), every value finite.
inline Tensor<float> as_steps(const Tensor<float>& t, const std::string& what) {
  const bool ok = (t.dim() == 2 || t.dim() == 3) && t.size(-1) == 3 && t.size(-2) >= 1;
  EPONA_CHECK(ok, what, ": a trajectory has shape (W, 3) or (S, W, 3) with W >= 1 waypoints of [x, y, yaw], got ",
              shape_str(t.shape()));
  const auto steps = t.dim() == 3 ? t : t.reshape({1, t.size(0), 3});
  const std::int64_t W = steps.size(1);
  for (std::int64_t i = 0; i < steps.numel(); ++i)
    EPONA_CHECK(std::isfinite(steps.data()[i]), what, ": step ", i / (3 * W), ", waypoint ", (i / 3) % W, ": ",
                poses_detail::kMotionNames[i % 3], " = ", steps.data()[i], " is not finite");
  return steps;
}

inline std::string lower_ext(const std::filesystem::path& p) { return poses_detail::lower(p.extension().string()); }

}  // namespace traj_detail

// ---- writers ----------------------------------------------------------------------------

inline std::string trajectory_to_csv(const Tensor<float>& traj) {
  const auto t = traj_detail::as_steps(traj, "trajectory_to_csv");
  std::string out =
      "# epona planned trajectory: waypoint n of a step is the ego pose n+1 frames after the step's current\n"
      "# frame, in that frame's ego coordinates: x metres forward, y metres left, yaw degrees (left turn > 0)\n";
  out += traj_detail::kCsvHeader;
  out += '\n';
  for (std::int64_t s = 0; s < t.size(0); ++s)
    for (std::int64_t w = 0; w < t.size(1); ++w) {
      out += std::to_string(s) + ',' + std::to_string(w);
      for (int k = 0; k < 3; ++k) {
        out += ',';
        traj_detail::append_float(out, t.at(s, w, k));
      }
      out += '\n';
    }
  return out;
}

// The hypotheses a plan was chosen from (model::PlanFan, written beside the chosen plan).
struct TrajectoryFan {
  Tensor<float> hypotheses;                  // (K, W, 3)
  std::string rule;                          // how the plan was chosen ("medoid", "mean")
  std::optional<std::int64_t> chosen_index;  // the chosen hypothesis, where the rule picks one
  std::vector<double> spread_m;              // per waypoint
};

namespace traj_detail {

// (S, W, 3) as a JSON list of S lists of W [x, y, yaw].
inline void append_steps(std::string& out, const Tensor<float>& t) {
  out += "[";
  for (std::int64_t s = 0; s < t.size(0); ++s) {
    out += s ? ",\n  [" : "\n  [";
    for (std::int64_t w = 0; w < t.size(1); ++w) {
      out += w ? ", [" : "[";
      for (int k = 0; k < 3; ++k) {
        if (k) out += ", ";
        traj_detail::append_float(out, t.at(s, w, k));
      }
      out += ']';
    }
    out += ']';
  }
  out += "\n ]";
}

inline void append_fan(std::string& out, const TrajectoryFan& fan) {
  out += ",\n \"hypotheses\": ";
  append_steps(out, as_steps(fan.hypotheses, "trajectory hypotheses"));
  out += ",\n \"choice\": {\"rule\": \"" + fan.rule + "\", \"index\": " +
         (fan.chosen_index ? std::to_string(*fan.chosen_index) : std::string("null")) + "},\n \"spread_m\": [";
  for (std::size_t w = 0; w < fan.spread_m.size(); ++w) {
    if (w) out += ", ";
    append_float(out, static_cast<float>(fan.spread_m[w]));
  }
  out += "]";
}

}  // namespace traj_detail

// {"format", "units", "steps": [[[x, y, yaw], ...], ...]}, and with a fan its "hypotheses",
// "choice" {"rule", "index"} and "spread_m".
inline std::string trajectory_to_json(const Tensor<float>& traj, const TrajectoryFan* fan = nullptr) {
  const auto t = traj_detail::as_steps(traj, "trajectory_to_json");
  std::string out = "{\"format\": \"";
  out += traj_detail::kFormat;
  out += "\",\n \"units\": {\"x\": \"m, forward\", \"y\": \"m, left\", \"yaw\": \"deg, left turn positive\"},\n";
  out += " \"steps\": ";
  traj_detail::append_steps(out, t);
  if (fan) traj_detail::append_fan(out, *fan);
  out += "\n}\n";
  return out;
}

// trajectory.json with the hypotheses it was chosen from, atomically.
inline void write_trajectory_json(const std::filesystem::path& path, const Tensor<float>& traj, const TrajectoryFan& fan) {
  write_atomically(path, trajectory_to_json(traj, &fan));
}

// Writes (W, 3) or (S, W, 3) as .csv, .json or .npy (by extension), atomically.
inline void write_trajectory(const std::filesystem::path& path, const Tensor<float>& traj) {
  const std::string ext = traj_detail::lower_ext(path);
  if (ext == ".csv") return write_atomically(path, trajectory_to_csv(traj));
  if (ext == ".json") return write_atomically(path, trajectory_to_json(traj));
  if (ext == ".npy") return write_npy(path, traj_detail::as_steps(traj, path.string()));
  fail(path.string(), ": unknown trajectory file type '", ext, "' (expected .csv, .json or .npy)");
}

// ---- readers ----------------------------------------------------------------------------

namespace traj_detail {

// The keys of a TrajectoryFan: a plan's hypotheses, read past (the plan is "steps").
inline bool is_fan_key(const std::string& key) { return key == "hypotheses" || key == "choice" || key == "spread_m"; }

// Collects rows in file order and checks the (step, waypoint) grid is complete and ordered.
struct GridBuilder {
  std::vector<float> values;
  std::int64_t steps = 0, waypoints = -1, next_waypoint = 0;

  template <class Where>
  void add(std::int64_t step, std::int64_t waypoint, const double (&v)[3], Where&& where) {
    if (waypoint == 0 && steps > 0) close_step(where);  // a new step begins
    const std::int64_t want_step = waypoint == 0 || steps == 0 ? steps : steps - 1;
    EPONA_CHECK(step == want_step && waypoint == next_waypoint, where(), ": expected step ", want_step, ", waypoint ",
                next_waypoint, " (rows in order, waypoints 0..W-1 per step), got step ", step, ", waypoint ", waypoint);
    EPONA_CHECK(waypoints < 0 || waypoint < waypoints, where(), ": step ", step, " has more waypoints than the ",
                waypoints, " of the steps before it");
    if (waypoint == 0) ++steps;
    ++next_waypoint;
    poses_detail::check_motion(v, where);
    values.insert(values.end(), v, v + 3);
  }
  template <class Where>
  void close_step(Where&& where) {
    if (waypoints < 0) waypoints = next_waypoint;
    EPONA_CHECK(next_waypoint == waypoints, where(), ": step ", steps - 1, " has ", next_waypoint,
                " waypoints, the steps before it have ", waypoints);
    next_waypoint = 0;
  }
  Tensor<float> finish(const std::string& source) {
    EPONA_CHECK(steps > 0, source, ": no trajectory rows in the file");
    close_step([&] { return source + ": at the end"; });
    Tensor<float> t({steps, waypoints, 3});
    std::copy(values.begin(), values.end(), t.data());
    return t;
  }
};

// Whether the first non-comment line of a CSV is a trajectory header (first column "step").
inline bool csv_starts_with_step(std::string_view text) {
  bool step = false;
  poses_detail::for_each_csv_line(text, [&](std::size_t, std::string_view line) {
    step = poses_detail::lower(poses_detail::split_fields(line).front()) == "step";
    return false;
  });
  return step;
}

inline bool parse_index(std::string_view f, std::int64_t& out) {
  const auto r = std::from_chars(f.data(), f.data() + f.size(), out);
  return !f.empty() && r.ec == std::errc() && r.ptr == f.data() + f.size() && out >= 0;
}

}  // namespace traj_detail

// CSV as written by trajectory_to_csv: '#' comments, the header step,waypoint,x,y,yaw, rows in order.
inline Tensor<float> parse_trajectory_csv(std::string_view text, const std::string& source) {
  using namespace poses_detail;
  traj_detail::GridBuilder grid;
  bool header_seen = false;
  for_each_csv_line(text, [&](std::size_t line_no, std::string_view line) {
    const auto where = [&] { return epona::detail::concat(source, ": line ", line_no); };
    const auto fields = split_fields(line);
    if (!header_seen) {
      std::string joined;
      for (auto f : fields) {
        if (!joined.empty()) joined += ',';
        joined += lower(f);
      }
      EPONA_CHECK(joined == traj_detail::kCsvHeader, where(), ": expected the header '", traj_detail::kCsvHeader,
                  "', got '", printable(line), "'");
      header_seen = true;
      return true;
    }
    EPONA_CHECK(fields.size() == 5, where(), ": expected 5 values (step, waypoint, x, y, yaw), got ",
                poses_detail::field_count(fields));
    std::int64_t step, waypoint;
    EPONA_CHECK(traj_detail::parse_index(fields[0], step) && traj_detail::parse_index(fields[1], waypoint), where(),
                ": step and waypoint must be non-negative integers, got '", printable(fields[0]), "', '",
                printable(fields[1]), "'");
    double v[3];
    for (int k = 0; k < 3; ++k)
      EPONA_CHECK(parse_number(fields[2 + k], v[k]), where(), ": ", kMotionNames[k], " = '", printable(fields[2 + k]),
                  "' is not a number");
    grid.add(step, waypoint, v, where);
    return true;
  });
  EPONA_CHECK(header_seen, source, ": empty file (expected the header '", traj_detail::kCsvHeader, "')");
  return grid.finish(source);
}

// JSON as written by trajectory_to_json: {"format": "epona-trajectory", "units": {...},
// "steps": [[[x, y, yaw], ...], ...]} ("format" and "units" optional; a fan's keys are skipped).
inline Tensor<float> parse_trajectory_json(std::string_view text, const std::string& source) {
  const nlohmann::json j = io::parse_json(text, source);
  EPONA_CHECK(j.is_object() && j.contains("steps"), source, ": expected an object with \"steps\": [[[x, y, yaw], ...], ...]");
  for (const auto& [key, value] : j.items())
    EPONA_CHECK(key == "steps" || key == "units" || key == "format" || traj_detail::is_fan_key(key), source,
                ": unexpected key '", printable(key), "'");
  if (j.contains("format"))
    EPONA_CHECK(j["format"] == traj_detail::kFormat, source, ": \"format\" is ", json_brief(j["format"]), ", expected \"",
                traj_detail::kFormat, "\"");
  const auto& steps = j["steps"];
  EPONA_CHECK(steps.is_array(), source, ": \"steps\" must be a list of steps");
  traj_detail::GridBuilder grid;
  for (std::size_t s = 0; s < steps.size(); ++s) {
    EPONA_CHECK(steps[s].is_array() && !steps[s].empty(), source, ": step ", s, " must be a non-empty list of waypoints");
    for (std::size_t w = 0; w < steps[s].size(); ++w) {
      const std::string where = epona::detail::concat(source, ": step ", s, ", waypoint ", w);
      const auto& e = steps[s][w];
      EPONA_CHECK(e.is_array() && e.size() == 3, where, ": expected [x, y, yaw], got ", json_brief(e));
      const double v[3] = {poses_detail::json_number(e[0], "x", where), poses_detail::json_number(e[1], "y", where),
                           poses_detail::json_number(e[2], "yaw", where)};
      grid.add(static_cast<std::int64_t>(s), static_cast<std::int64_t>(w), v, [&] { return where; });
    }
  }
  return grid.finish(source);
}

// Reads a trajectory file (.csv, .json, .npy) back as (S, W, 3).
inline Tensor<float> read_trajectory(const std::filesystem::path& path) {
  const std::string ext = traj_detail::lower_ext(path);
  if (ext == ".csv") return parse_trajectory_csv(poses_detail::as_text(read_whole_file(path)), path.string());
  if (ext == ".json") return parse_trajectory_json(poses_detail::as_text(read_whole_file(path)), path.string());
  if (ext == ".npy") return traj_detail::as_steps(read_npy<float>(path).values, path.string());
  fail(path.string(), ": unknown trajectory file type '", ext, "' (expected .csv, .json or .npy)");
}

// The action of each step of a trajectory: waypoint 0 = the motion from the step's current
// frame into the next one, which is what the self-predicted rollout feeds back (test_free.py).
inline PoseSequence first_waypoints(const Tensor<float>& traj) {
  const auto t = traj_detail::as_steps(traj, "first_waypoints");
  PoseSequence s;
  for (std::int64_t i = 0; i < t.size(0); ++i) {
    s.x.push_back(t.at(i, 0, 0));
    s.y.push_back(t.at(i, 0, 1));
    s.yaw.push_back(t.at(i, 0, 2));
  }
  return s;
}

// Per-step actions for `generate --trajectory FILE`: a planned trajectory written by epona
// (CSV with the step,waypoint,... header, JSON with "steps", .npy of shape (S, W, 3)) gives the
// first waypoint of each step (a replay of a rollout's own choices); any other pose file
// (load_poses: x,y,yaw rows, JSON poses, absolute poses, the demo's npy pair) gives its rows,
// one per-frame motion per step.
inline PoseSequence read_actions(const std::filesystem::path& path) {
  const std::string ext = traj_detail::lower_ext(path);
  bool planned = false;
  if (ext == ".csv") {
    planned = traj_detail::csv_starts_with_step(poses_detail::as_text(read_whole_file(path)));
  } else if (ext == ".json") {
    const auto j = io::parse_json(poses_detail::as_text(read_whole_file(path)), path.string());
    planned = j.is_object() && j.contains("steps");
  } else if (ext == ".npy") {
    const auto a = read_npy<float>(path).values;
    planned = a.dim() == 3 && a.size(-1) == 3;
  }
  return planned ? first_waypoints(read_trajectory(path)) : load_poses(path);
}

}  // namespace epona::io
