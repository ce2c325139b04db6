// epona/domain/poses.hpp — the per-frame ego motion a user gives with a clip: CSV, JSON, the
// official demo's pose.npy + yaw.npy (dataset/dataset_demo.py), or absolute 4x4 ego-to-world
// poses turned into motions by get_rel_pose (utils/preprocess.py). Every reader validates
// (finite numbers, column counts, matching lengths) and names the file and row in its errors.
//
// Meaning of the result (docs/api.md, actions): entry i is the motion from
// frame i-1 to frame i, expressed in the ego frame of frame i-1 — x metres forward, y metres
// to the LEFT, yaw degrees, positive = turning left (nuPlan's ego frame; the official README's
// "right is positive" for y contradicts its own data pipeline, whose numbers we follow). Entry 0
// has no previous frame: it is zero motion when derived from absolute poses, and whatever the
// user wrote otherwise. At the nuPlan config's 5 Hz, a car at 36 km/h moves x = 2 m per frame.
#pragma once

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "epona/core/error.hpp"
#include "epona/core/printable.hpp"
#include "epona/core/tensor.hpp"
#include "epona/io/json_reader.hpp"
#include "epona/io/limits.hpp"
#include "epona/io/npy.hpp"
#include "epona/model/relative_pose.hpp"

namespace epona::io {

struct PoseSequence {
  std::vector<float> x, y, yaw;  // metres, metres (left positive), degrees (left turn positive)

  std::size_t size() const { return x.size(); }
  bool empty() const { return x.empty(); }

  // The official step inputs: rel_pose (1, N, 2) and rel_yaw (1, N, 1).
  Tensor<float> pose_tensor() const {
    Tensor<float> t({1, static_cast<std::int64_t>(size()), 2});
    for (std::size_t i = 0; i < size(); ++i) t.data()[2 * i] = x[i], t.data()[2 * i + 1] = y[i];
    return t;
  }
  Tensor<float> yaw_tensor() const {
    Tensor<float> t({1, static_cast<std::int64_t>(size()), 1});
    std::copy(yaw.begin(), yaw.end(), t.data());
    return t;
  }

  // Motions [first, first + count): a clip's window, or the first actions of a future.
  PoseSequence slice(std::size_t first, std::size_t count) const {
    EPONA_CHECK(first <= size() && count <= size() - first, "PoseSequence::slice: [", first, ", ", first + count,
                ") of ", size(), " motion(s)");
    const auto part = [&](const std::vector<float>& v) {
      return std::vector<float>(v.begin() + std::ptrdiff_t(first), v.begin() + std::ptrdiff_t(first + count));
    };
    return {part(x), part(y), part(yaw)};
  }
};

namespace poses_detail {

inline constexpr const char* kMotionNames[3] = {"x", "y", "yaw"};

// Doubles below this magnitude round to a finite float (FLT_MAX plus half its ulp, exclusive).
inline constexpr double kFloatOverflow = 0x1.ffffffp+127;

// Checks that x, y, yaw are finite in fp32; `where` says which file and row they came from
// (called only on error).
template <class Where>
void check_motion(const double (&v)[3], Where&& where) {
  for (int k = 0; k < 3; ++k)
    EPONA_CHECK(std::isfinite(v[k]) && std::fabs(v[k]) < kFloatOverflow, where(), ": ", kMotionNames[k], " = ", v[k],
                " is not a finite number in float32");
}

template <class Where>
void push_motion(PoseSequence& s, double x, double y, double yaw, Where&& where) {
  check_motion({x, y, yaw}, where);
  s.x.push_back(static_cast<float>(x));
  s.y.push_back(static_cast<float>(y));
  s.yaw.push_back(static_cast<float>(yaw));
}

inline std::string_view trim(std::string_view s) {
  const auto b = s.find_first_not_of(" \t\r");
  if (b == std::string_view::npos) return {};
  return s.substr(b, s.find_last_not_of(" \t\r") - b + 1);
}

// Fields of a CSV line: comma-separated when it has a comma, else whitespace-separated. At most
// limits::kCsvFields + 1 fields are split off (the last holds the rest), so a line of 96M commas
// costs one field vector of 17, not 96M views; more_fields() tells whether the cut happened.
inline std::vector<std::string_view> split_fields(std::string_view line) {
  std::vector<std::string_view> out;
  const auto full = [&] { return out.size() == limits::kCsvFields; };
  if (line.find(',') != std::string_view::npos) {
    std::size_t start = 0;
    for (;;) {
      if (full()) {
        out.push_back(line.substr(start));
        break;
      }
      const auto comma = line.find(',', start);
      out.push_back(trim(line.substr(start, comma - start)));
      if (comma == std::string_view::npos) break;
      start = comma + 1;
    }
  } else {
    std::size_t i = 0;
    while ((i = line.find_first_not_of(" \t", i)) != std::string_view::npos) {
      if (full()) {
        out.push_back(line.substr(i));
        break;
      }
      const auto end = std::min(line.find_first_of(" \t", i), line.size());
      out.push_back(line.substr(i, end - i));
      i = end;
    }
  }
  return out;
}

// "3", or "more than 16" when split_fields stopped splitting.
inline std::string field_count(const std::vector<std::string_view>& fields) {
  return fields.size() > limits::kCsvFields ? "more than " + std::to_string(limits::kCsvFields)
                                            : std::to_string(fields.size());
}

// A whole field as a number (a leading '+' allowed); false if it is not one.
inline bool parse_number(std::string_view field, double& out) {
  if (!field.empty() && field.front() == '+') field.remove_prefix(1);
  if (field.empty()) return false;
  const auto r = std::from_chars(field.data(), field.data() + field.size(), out);
  return r.ec == std::errc() && r.ptr == field.data() + field.size();
}

// Calls fn(line_number, content) for every line that is not blank once its '#' comment and
// surrounding blanks are removed (a UTF-8 byte-order mark is skipped); fn returns false to stop.
template <class Fn>
void for_each_csv_line(std::string_view text, Fn&& fn) {
  if (text.substr(0, 3) == "\xEF\xBB\xBF") text.remove_prefix(3);
  std::size_t line_no = 0;
  for (std::size_t pos = 0; pos <= text.size();) {
    const auto nl = std::min(text.find('\n', pos), text.size());
    const std::string_view raw = text.substr(pos, nl - pos);
    pos = nl + 1;
    ++line_no;
    const std::string_view line = trim(raw.substr(0, raw.find('#')));
    if (!line.empty() && !fn(line_no, line)) return;
  }
}

inline std::string lower(std::string_view s) {
  std::string out(s);
  for (auto& c : out) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return out;
}

// Column order from a header naming x, y, yaw once each, in any order.
inline std::array<int, 3> header_columns(const std::vector<std::string_view>& fields, std::string_view line,
                                         const std::string& where) {
  std::array<int, 3> col{-1, -1, -1};
  bool ok = fields.size() == 3;
  for (std::size_t f = 0; ok && f < fields.size(); ++f) {
    const std::string name = lower(fields[f]);
    const auto k = std::find(std::begin(kMotionNames), std::end(kMotionNames), name) - std::begin(kMotionNames);
    ok = k < 3 && col[k] < 0;
    if (ok) col[k] = static_cast<int>(f);
  }
  EPONA_CHECK(ok, where, ": the header must name the three columns x, y, yaw (got '", printable(line),
              "'); or leave the header out and give x, y, yaw in that order");
  return col;
}

inline double json_number(const nlohmann::json& v, const char* what, const std::string& where) {
  EPONA_CHECK(v.is_number(), where, ": ", what, " must be a number, got ", json_brief(v));
  return v.get<double>();
}

inline std::string_view as_text(const std::vector<std::byte>& bytes) {
  return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

inline void check_not_empty(const PoseSequence& s, const std::string& source) {
  EPONA_CHECK(!s.empty(), source, ": no poses in the file");
}

}  // namespace poses_detail

// ---- CSV: one row per frame, x,y,yaw (header optional, any column order with a header) ----

inline PoseSequence parse_pose_csv(std::string_view text, const std::string& source) {
  using namespace poses_detail;
  PoseSequence s;
  std::array<int, 3> col{0, 1, 2};
  bool first_row = true;
  for_each_csv_line(text, [&](std::size_t line_no, std::string_view line) {
    const auto where = [&] { return epona::detail::concat(source, ": line ", line_no); };
    const auto fields = split_fields(line);
    double v[3];
    const bool numeric = fields.size() == 3 && parse_number(fields[0], v[0]) && parse_number(fields[1], v[1]) &&
                         parse_number(fields[2], v[2]);
    const bool header = first_row && !numeric && std::isalpha(static_cast<unsigned char>(line.front())) &&
                        !parse_number(fields[0], v[0]);  // "nan,..." is a (bad) data row
    first_row = false;
    if (header) {
      col = header_columns(fields, line, where());
      return true;
    }
    EPONA_CHECK(fields.size() == 3, where(), ": expected 3 values (x, y, yaw), got ", field_count(fields), ": '",
                printable(line), "'");
    for (int k = 0; k < 3; ++k)
      EPONA_CHECK(parse_number(fields[col[k]], v[k]), where(), ": ", kMotionNames[k], " = '", printable(fields[col[k]]),
                  "' is not a number");
    push_motion(s, v[0], v[1], v[2], where);
    return true;
  });
  check_not_empty(s, source);
  return s;
}

// ---- JSON: {"poses": [[x, y, yaw], ...]}, [[x, y, yaw], ...], [{"x":, "y":, "yaw":}, ...],
//      or {"absolute": [4x4, ...]} (ego-to-world matrices, row-major nested arrays) ----------

namespace poses_detail {

inline void push_json_entry(PoseSequence& s, const nlohmann::json& e, std::size_t i, const std::string& source) {
  const std::string where = epona::detail::concat(source, ": pose ", i);
  if (e.is_array()) {
    EPONA_CHECK(e.size() == 3, where, ": expected [x, y, yaw], got ", e.size(), " values");
    push_motion(s, json_number(e[0], "x", where), json_number(e[1], "y", where), json_number(e[2], "yaw", where),
                [&] { return where; });
    return;
  }
  EPONA_CHECK(e.is_object(), where, ": expected [x, y, yaw] or {\"x\": .., \"y\": .., \"yaw\": ..}, got ", json_brief(e));
  for (const auto& [key, _] : e.items())
    EPONA_CHECK(key == "x" || key == "y" || key == "yaw", where, ": unexpected key '", printable(key),
                "' (expected x, y, yaw)");
  for (const char* key : {"x", "y", "yaw"}) EPONA_CHECK(e.contains(key), where, ": missing '", key, "'");
  push_motion(s, json_number(e["x"], "x", where), json_number(e["y"], "y", where), json_number(e["yaw"], "yaw", where),
              [&] { return where; });
}

// (N, 4, 4) nested JSON arrays -> a (1, N, 4, 4) double tensor.
inline Tensor<double> json_matrices(const nlohmann::json& a, const std::string& source) {
  EPONA_CHECK(a.is_array(), source, ": \"absolute\" must be a list of 4x4 matrices");
  Tensor<double> t({1, static_cast<std::int64_t>(a.size()), 4, 4});
  for (std::size_t i = 0; i < a.size(); ++i) {
    const std::string where = epona::detail::concat(source, ": absolute pose ", i);
    EPONA_CHECK(a[i].is_array() && a[i].size() == 4, where, ": expected a 4x4 matrix (4 rows of 4 numbers)");
    for (std::size_t r = 0; r < 4; ++r) {
      EPONA_CHECK(a[i][r].is_array() && a[i][r].size() == 4, where, ": row ", r, " must hold 4 numbers");
      for (std::size_t c = 0; c < 4; ++c)
        t.data()[i * 16 + r * 4 + c] = json_number(a[i][r][c], "every matrix entry", where);
    }
  }
  return t;
}

}  // namespace poses_detail

// Motions from absolute ego-to-world poses (1, N, 4, 4) or (N, 4, 4): get_rel_pose (entry 0 is
// zero motion). The bottom row must be [0, 0, 0, 1]; that catches transposed (column-major) input.
template <class S>
PoseSequence poses_from_absolute(const Tensor<S>& absolute, const std::string& source) {
  const bool batched = absolute.dim() == 4 && absolute.size(0) == 1;
  EPONA_CHECK((absolute.dim() == 3 || batched) && absolute.size(-1) == 4 && absolute.size(-2) == 4, source,
              ": absolute poses must have shape (N, 4, 4) or (1, N, 4, 4), got ", shape_str(absolute.shape()));
  const std::int64_t n = absolute.size(-3);
  EPONA_CHECK(n >= 1, source, ": no poses in the file");
  for (std::int64_t i = 0; i < n; ++i) {
    const S* m = absolute.data() + 16 * i;
    const bool affine = std::fabs(m[12]) <= 1e-6 && std::fabs(m[13]) <= 1e-6 && std::fabs(m[14]) <= 1e-6 &&
                        std::fabs(m[15] - 1) <= 1e-6;
    EPONA_CHECK(affine, source, ": absolute pose ", i, ": bottom row must be [0, 0, 0, 1], got [", m[12], ", ",
                m[13], ", ", m[14], ", ", m[15], "] (a transposed matrix? rows are [R | t])");
  }
  model::RelativePoses rel;
  try {
    rel = model::get_rel_pose(absolute.reshape({1, n, 4, 4}));
  } catch (const Error& e) {
    fail(source, ": ", e.what());
  }
  PoseSequence s;
  for (std::int64_t i = 0; i < n; ++i)
    poses_detail::push_motion(s, rel.pose.data()[2 * i], rel.pose.data()[2 * i + 1], rel.yaw.data()[i],
                              [&] { return epona::detail::concat(source, ": motion into absolute pose ", i); });
  return s;
}

inline PoseSequence parse_pose_json(std::string_view text, const std::string& source) {
  using namespace poses_detail;
  const nlohmann::json j = io::parse_json(text, source);
  const nlohmann::json* list = &j;
  if (j.is_object()) {
    for (const auto& [key, _] : j.items())
      EPONA_CHECK(key == "poses" || key == "absolute", source, ": unexpected key '", printable(key),
                  "' (expected \"poses\": [[x, y, yaw], ...] or \"absolute\": [4x4 matrices])");
    EPONA_CHECK(j.size() == 1, source, ": give either \"poses\" or \"absolute\", not both");
    if (j.contains("absolute")) return poses_from_absolute(json_matrices(j["absolute"], source), source);
    list = &j["poses"];
  }
  EPONA_CHECK(list->is_array(), source, ": expected a list of poses, got ", list->type_name());
  PoseSequence s;
  for (std::size_t i = 0; i < list->size(); ++i) push_json_entry(s, (*list)[i], i, source);
  check_not_empty(s, source);
  return s;
}

// ---- the official demo's files: pose.npy (N, 2) or (1, N, 2) metres, yaw.npy (N,), (N, 1)
//      or (1, N, 1) degrees; both are already per-frame motions (no get_rel_pose) ------------

inline PoseSequence read_demo_poses(const std::filesystem::path& pose_npy, const std::filesystem::path& yaw_npy) {
  const auto pose = read_npy<double>(pose_npy).values;
  const auto yaw = read_npy<double>(yaw_npy).values;
  const Shape& ps = pose.shape();
  const Shape& ys = yaw.shape();
  const bool pose_ok = (ps.size() == 2 && ps[1] == 2) || (ps.size() == 3 && ps[0] == 1 && ps[2] == 2);
  EPONA_CHECK(pose_ok, pose_npy.string(), ": expected shape (N, 2) or (1, N, 2) (x, y per frame), got ",
              shape_str(ps));
  const bool yaw_ok = ys.size() == 1 || (ys.size() == 2 && ys[1] == 1) || (ys.size() == 3 && ys[0] == 1 && ys[2] == 1);
  EPONA_CHECK(yaw_ok, yaw_npy.string(), ": expected shape (N,), (N, 1) or (1, N, 1) (yaw per frame), got ",
              shape_str(ys));
  const std::int64_t n = pose.numel() / 2;
  EPONA_CHECK(yaw.numel() == n, pose_npy.string(), " holds ", n, " poses but ", yaw_npy.string(), " holds ",
              yaw.numel(), " yaws; they must have one entry per frame each");
  EPONA_CHECK(n >= 1, pose_npy.string(), ": no poses in the file");
  PoseSequence s;
  for (std::int64_t i = 0; i < n; ++i)
    poses_detail::push_motion(s, pose.data()[2 * i], pose.data()[2 * i + 1], yaw.data()[i], [&] {
      return epona::detail::concat(pose_npy.string(), " / ", yaw_npy.filename().string(), ": row ", i);
    });
  return s;
}

// ---- one entry point: by folder or extension ------------------------------------------

// A folder -> pose.npy + yaw.npy inside it; .csv/.txt -> CSV; .json -> JSON; .npy -> absolute
// poses (N, 4, 4) / (1, N, 4, 4), x, y, yaw rows (N, 3), or a demo pose.npy with yaw.npy beside it.
inline PoseSequence load_poses(const std::filesystem::path& path) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (fs::is_directory(path, ec)) return read_demo_poses(path / "pose.npy", path / "yaw.npy");
  const std::string ext = poses_detail::lower(path.extension().string());
  if (ext == ".csv" || ext == ".txt") return parse_pose_csv(poses_detail::as_text(read_whole_file(path)), path.string());
  if (ext == ".json") return parse_pose_json(poses_detail::as_text(read_whole_file(path)), path.string());
  if (ext == ".npy") {
    const auto a = read_npy<double>(path).values;
    if (a.dim() >= 3 && a.size(-1) == 4 && a.size(-2) == 4) return poses_from_absolute(a, path.string());
    if (a.dim() == 2 && a.size(1) == 3) {  // (N, 3): x, y, yaw rows, like the CSV
      PoseSequence s;
      for (std::int64_t i = 0; i < a.size(0); ++i)
        poses_detail::push_motion(s, a.at(i, 0), a.at(i, 1), a.at(i, 2),
                                  [&] { return epona::detail::concat(path.string(), ": row ", i); });
      poses_detail::check_not_empty(s, path.string());
      return s;
    }
    const auto yaw = path.parent_path() / "yaw.npy";
    EPONA_CHECK(path.filename() == "pose.npy" && fs::exists(yaw, ec), path.string(), ": a .npy of shape ",
                shape_str(a.shape()),
                " is none of: absolute poses (N, 4, 4), x, y, yaw rows (N, 3), a demo pose.npy with yaw.npy beside it");
    return read_demo_poses(path, yaw);
  }
  fail(path.string(), ": unknown pose file type '", ext,
       "' (expected .csv, .txt, .json, .npy, or a folder with pose.npy and yaw.npy)");
}

}  // namespace epona::io
