// Tests for epona/domain/poses.hpp: every accepted input form read back to the exact numbers it
// holds (CSV/JSON values are parsed as double and rounded to fp32 once), absolute poses
// against the torch float32 references of scripts/make_pose_fixtures.py (tolerance
// 1e-5·max(1, |want|)), and every malformed input ending in an error that names file and row.
#include <doctest/doctest.h>

#include <filesystem>
#include <fstream>
#include <random>
#include <string>

#include <nlohmann/json.hpp>

#include "epona/domain/poses.hpp"
#include "../temp_dir.hpp"
#include "../files.hpp"

using namespace epona;
using epona::test::read_json;
using epona::test::TempDir;
namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const fs::path kData = fs::path(EPONA_TEST_DATA_DIR) / "poses";

io::PoseSequence pose_csv(const std::string& text) { return io::parse_pose_csv(text, "p.csv"); }
io::PoseSequence pose_json(const std::string& text) { return io::parse_pose_json(text, "p.json"); }

void check_sequence(const io::PoseSequence& s, const std::vector<double>& x, const std::vector<double>& y,
                    const std::vector<double>& yaw) {
  REQUIRE(s.size() == x.size());
  REQUIRE(s.y.size() == x.size());
  REQUIRE(s.yaw.size() == x.size());
  for (std::size_t i = 0; i < x.size(); ++i) {
    CHECK(s.x[i] == float(x[i]));
    CHECK(s.y[i] == float(y[i]));
    CHECK(s.yaw[i] == float(yaw[i]));
  }
}

// Relative motions from the torch reference for batch 0 of relative_pose.json.
void check_against_reference(const io::PoseSequence& s, const json& pose, const json& yaw) {
  REQUIRE(s.size() == pose.size());
  double worst = 0;
  for (std::size_t i = 0; i < s.size(); ++i) {
    const double want[3] = {pose[i][0].get<double>(), pose[i][1].get<double>(), yaw[i][0].get<double>()};
    const double got[3] = {s.x[i], s.y[i], s.yaw[i]};
    for (int k = 0; k < 3; ++k) worst = std::max(worst, std::fabs(got[k] - want[k]) / std::max(1.0, std::fabs(want[k])));
  }
  MESSAGE("absolute -> relative: max scaled error ", worst);
  CHECK(worst <= 1e-5);
}

}  // namespace

TEST_CASE("CSV: header or not, comments, whitespace, CRLF, BOM, column order") {
  check_sequence(pose_csv("x,y,yaw\n0,0,0\n1.5,-0.25,2\n"), {0, 1.5}, {0, -0.25}, {0, 2});
  check_sequence(pose_csv("# my drive\n\n 0.1 , 0.2 , 0.3 # first\n+4e-1,-5E-1,.6\n"), {0.1, 0.4}, {0.2, -0.5}, {0.3, 0.6});
  check_sequence(pose_csv("0.1 0.2\t0.3\n 1  2  3 \n"), {0.1, 1}, {0.2, 2}, {0.3, 3});
  check_sequence(pose_csv("\xEF\xBB\xBFX, Y, Yaw\r\n1,2,3\r\n"), {1}, {2}, {3});
  check_sequence(pose_csv("yaw,x,y\n3,1,2\n"), {1}, {2}, {3});
  check_sequence(pose_csv("1,2,3"), {1}, {2}, {3});  // no final newline
  const auto s = pose_csv("1,2,3\n4,5,6\n");
  const auto p = s.pose_tensor(), y = s.yaw_tensor();
  CHECK(p.shape() == Shape{1, 2, 2});
  CHECK(y.shape() == Shape{1, 2, 1});
  CHECK(p.at(0, 1, 0) == 4.f);
  CHECK(p.at(0, 1, 1) == 5.f);
  CHECK(y.at(0, 1, 0) == 6.f);
}

TEST_CASE("CSV: malformed files name the file and line") {
  struct Case {
    std::string text, expect;
  };
  const Case cases[] = {
      {"", "p.csv: no poses"},
      {"# only a comment\n\n", "p.csv: no poses"},
      {"x,y,yaw\n", "p.csv: no poses"},
      {"x,y,yaw\n1,2,3\n4,5\n", "p.csv: line 3: expected 3 values (x, y, yaw), got 2"},
      {"1,2,3,4\n", "line 1: expected 3 values"},
      {"1,2,3\n1,,3\n", "line 2: y = '' is not a number"},
      {"1,2,3\n1,2,3deg\n", "line 2: yaw = '3deg' is not a number"},
      {"1,2,3\nnan,2,3\n", "line 2: x = nan is not a finite number"},
      {"nan,2,3\n", "line 1: x = nan is not a finite number"},
      {"1,2,3\n1,inf,3\n", "line 2: y = inf is not a finite number"},
      {"1,2,1e39\n", "line 1: yaw = 1e+39 is not a finite number"},
      {"x,y,heading\n1,2,3\n", "line 1: the header must name the three columns x, y, yaw (got 'x,y,heading')"},
      {"x,x,yaw\n1,2,3\n", "the header must name"},
      {"x,y\n1,2\n", "the header must name"},
      {"1,2,3\nx,y,yaw\n", "line 2: x = 'x' is not a number"},
      {"1;2;3\n", "line 1: expected 3 values"},
  };
  for (const auto& c : cases) {
    CAPTURE(c.text);
    CHECK_THROWS_WITH_AS(pose_csv(c.text), doctest::Contains(c.expect.c_str()), Error);
  }
}

TEST_CASE("JSON: the three relative forms") {
  check_sequence(pose_json(R"({"poses": [[0, 0, 0], [1.25, -0.5, 3]]})"), {0, 1.25}, {0, -0.5}, {0, 3});
  check_sequence(pose_json(R"([[0.1, 0.2, 0.3]])"), {0.1}, {0.2}, {0.3});
  check_sequence(pose_json(R"([{"x": 1, "y": 2, "yaw": 3}, {"yaw": -6, "y": 5, "x": 4}])"), {1, 4}, {2, 5}, {3, -6});
}

TEST_CASE("JSON: malformed files name the file and entry") {
  struct Case {
    std::string text, expect;
  };
  const Case cases[] = {
      {"", "p.json: invalid JSON"},
      {"{\"poses\": [[1, 2, 3]]", "p.json: invalid JSON"},
      {"[[1, 2, NaN]]", "p.json: invalid JSON"},
      {"[]", "p.json: no poses"},
      {R"({"poses": []})", "p.json: no poses"},
      {R"({"pose": [[1, 2, 3]]})", "p.json: unexpected key 'pose'"},
      {R"({"poses": [[1, 2, 3]], "absolute": []})", "not both"},
      {R"({"poses": {"x": 1}})", "expected a list of poses, got object"},
      {R"("hello")", "expected a list of poses, got string"},
      {R"([[1, 2, 3], [1, 2]])", "p.json: pose 1: expected [x, y, yaw], got 2 values"},
      {R"([[1, 2, 3], [1, "2", 3]])", "p.json: pose 1: y must be a number, got \"2\""},
      {R"([[1, 2, 3], [1, null, 3]])", "pose 1: y must be a number, got null"},
      {R"([{"x": 1, "y": 2}])", "pose 0: missing 'yaw'"},
      {R"([{"x": 1, "y": 2, "yaw": 3, "z": 0}])", "pose 0: unexpected key 'z'"},
      {R"([[1, 2, 3], 7])", "pose 1: expected [x, y, yaw] or"},
      {R"([[1, 2, 1e39]])", "pose 0: yaw = 1e+39 is not a finite number"},
      {R"([[1, 2, 1e999]])", "p.json: invalid JSON: [json.exception.out_of_range.406] number overflow"},
  };
  for (const auto& c : cases) {
    CAPTURE(c.text);
    CHECK_THROWS_WITH_AS(pose_json(c.text), doctest::Contains(c.expect.c_str()), Error);
  }
}

TEST_CASE("absolute poses (JSON and .npy) -> per-frame motions via get_rel_pose") {
  const json ref = read_json(kData / "relative_pose.json");
  const json& abs0 = ref["absolute"][0];  // (16, 4, 4), exact fp32 values
  TempDir dir;
  const auto file = dir.write("abs.json", json{{"absolute", abs0}}.dump());
  check_against_reference(io::load_poses(file), ref["rel_pose"][0], ref["rel_yaw"][0]);
  check_against_reference(io::load_poses(kData / "absolute_n44_f4.npy"), ref["rel_pose"][0], ref["rel_yaw"][0]);
  check_against_reference(io::load_poses(kData / "absolute_1n44_f8.npy"), ref["rel_pose"][0], ref["rel_yaw"][0]);
  // World coordinates ~ 1e6 m in float64: the float64 reference is met.
  const auto utm = io::load_poses(kData / "absolute_utm_n44_f8.npy");
  const json& want = ref["utm"]["expected"];
  REQUIRE(utm.size() == want.size());
  for (std::size_t i = 0; i < utm.size(); ++i) {
    CHECK(utm.x[i] == doctest::Approx(want[i][0].get<double>()).epsilon(1e-5).scale(1));
    CHECK(utm.y[i] == doctest::Approx(want[i][1].get<double>()).epsilon(1e-5).scale(1));
    CHECK(utm.yaw[i] == doctest::Approx(want[i][2].get<double>()).epsilon(1e-5).scale(1));
  }
  CHECK(utm.x[0] == 0.f);  // entry 0: zero motion
}

TEST_CASE("absolute poses: malformed input is a named error") {
  json eye = json::array({{1, 0, 0, 5}, {0, 1, 0, 6}, {0, 0, 1, 7}, {0, 0, 0, 1}});
  json transposed = json::array({{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}, {5, 6, 7, 1}});
  json singular = json::array({{1, 0, 0, 5}, {0, 0, 0, 6}, {0, 0, 1, 7}, {0, 0, 0, 1}});
  auto abs = [](json list) { return json{{"absolute", std::move(list)}}.dump(); };
  CHECK_THROWS_WITH_AS(pose_json(abs(json::array({eye, transposed}))),
                       doctest::Contains("p.json: absolute pose 1: bottom row must be [0, 0, 0, 1], got [5, 6, 7, 1]"),
                       Error);
  CHECK_THROWS_WITH_AS(pose_json(abs(json::array({eye, singular, eye}))), doctest::Contains("singular"), Error);
  CHECK_THROWS_WITH_AS(pose_json(abs(json::array({eye, singular, eye}))),
                       doctest::Contains("p.json: get_rel_pose: from pose 1 to pose 2"), Error);
  CHECK_THROWS_WITH_AS(pose_json(abs(json::array({eye, json::array({{1, 0, 0}, {0, 1, 0}, {0, 0, 1}})}))),
                       doctest::Contains("absolute pose 1: expected a 4x4 matrix"), Error);
  json bad_entry = eye;
  bad_entry[2][3] = "7";
  CHECK_THROWS_WITH_AS(pose_json(abs(json::array({bad_entry}))),
                       doctest::Contains("absolute pose 0: every matrix entry must be a number"), Error);
  CHECK_THROWS_WITH_AS(pose_json(abs(json::array())), doctest::Contains("p.json: no poses"), Error);
  CHECK_THROWS_WITH_AS(pose_json(abs(json::object())), doctest::Contains("list of 4x4 matrices"), Error);
  CHECK_THROWS_WITH_AS(io::poses_from_absolute(Tensor<float>::zeros({2, 3, 4, 4}), "m.npy"),
                       doctest::Contains("m.npy: absolute poses must have shape (N, 4, 4) or (1, N, 4, 4)"), Error);
}

TEST_CASE("the official demo's pose.npy + yaw.npy in every accepted shape and dtype") {
  const json want = read_json(kData / "demo_expected.json");
  auto expect = [&](const io::PoseSequence& s, const char* xy, const char* yaw) {
    check_sequence(s, want[xy]["x"].get<std::vector<double>>(), want[xy]["y"].get<std::vector<double>>(),
                   want[yaw]["yaw"].get<std::vector<double>>());
  };
  expect(io::load_poses(kData / "demo_n2_f4"), "f4", "f4");                 // (N, 2) + (N,)
  expect(io::load_poses(kData / "demo_n2_f4" / "pose.npy"), "f4", "f4");    // the file itself
  expect(io::load_poses(kData / "demo_1n2_f8"), "f8", "f8");                // (1, N, 2) + (1, N, 1), f8
  expect(io::load_poses(kData / "demo_mixed"), "f4", "f8");                 // (N, 2) f4 + (N, 1) f8
  CHECK(io::load_poses(kData / "demo_n2_f4").size() == 14);  // all frames, not just the first axis
}

TEST_CASE("demo files: mismatches, NaN and wrong shapes name the files and row") {
  CHECK_THROWS_WITH_AS(io::load_poses(kData / "demo_mismatch"), doctest::Contains("holds 14 poses but"), Error);
  CHECK_THROWS_WITH_AS(io::load_poses(kData / "demo_mismatch"), doctest::Contains("yaw.npy holds 13 yaws"), Error);
  CHECK_THROWS_WITH_AS(io::load_poses(kData / "demo_nan"),
                       doctest::Contains("demo_nan/pose.npy / yaw.npy: row 5: y = nan is not a finite number"), Error);
  CHECK_THROWS_WITH_AS(io::load_poses(kData / "demo_badshape"),
                       doctest::Contains("pose.npy: expected shape (N, 2) or (1, N, 2) (x, y per frame), got (14, 3)"),
                       Error);
  CHECK_THROWS_WITH_AS(io::read_demo_poses(kData / "demo_n2_f4" / "pose.npy", kData / "demo_n2_f4" / "pose.npy"),
                       doctest::Contains("expected shape (N,), (N, 1) or (1, N, 1)"), Error);
  CHECK_THROWS_WITH_AS(io::load_poses(kData / "npy"), doctest::Contains("npy/pose.npy: not found"), Error);
}

TEST_CASE("load_poses dispatch errors") {
  TempDir dir;
  CHECK_THROWS_WITH_AS(io::load_poses(dir.write("p.yaml", "x: 1")), doctest::Contains("unknown pose file type '.yaml'"),
                       Error);
  CHECK_THROWS_WITH_AS(io::load_poses(kData / "npy" / "f4_v1.npy"),
                       doctest::Contains("f4_v1.npy: a .npy of shape (3, 4) is none of: absolute poses"), Error);
  // (N, 3) rows of x, y, yaw
  Tensor<float> rows({2, 3});
  for (int i = 0; i < 6; ++i) rows.data()[i] = 0.5f * float(i);
  io::write_npy(dir.path / "rows.npy", rows);
  check_sequence(io::load_poses(dir.path / "rows.npy"), {0, 1.5}, {0.5, 2}, {1, 2.5});
  rows.at(1, 2) = NAN;
  io::write_npy(dir.path / "rows.npy", rows);
  CHECK_THROWS_WITH_AS(io::load_poses(dir.path / "rows.npy"), doctest::Contains("rows.npy: row 1: yaw = nan"), Error);
  CHECK_THROWS_WITH_AS(io::load_poses(dir.path / "missing.csv"), doctest::Contains("missing.csv: not found"), Error);
  check_sequence(io::load_poses(dir.write("p.CSV", "x,y,yaw\n1,2,3\n")), {1}, {2}, {3});
  check_sequence(io::load_poses(dir.write("p.txt", "1 2 3\n")), {1}, {2}, {3});
}

TEST_CASE("random corruption of CSV and JSON pose files: a PoseSequence or an epona::Error, nothing else") {
  const std::string seeds[] = {
      "# drive\nx,y,yaw\n0,0,0\n1.5,-0.25,2\n3e-1 , 4 , -5\n",
      R"({"poses": [[0, 0, 0], [1.25, -0.5, 3]]})",
      R"([{"x": 1, "y": 2, "yaw": 3}])",
      R"({"absolute": [[[1, 0, 0, 5], [0, 1, 0, 6], [0, 0, 1, 7], [0, 0, 0, 1]], [[0, -1, 0, 5], [1, 0, 0, 6], [0, 0, 1, 7], [0, 0, 0, 1]]]})",
  };
  std::mt19937 gen(11);
  const std::string alphabet = "0123456789.,-+eE#\n\r \t[]{}\":xyawbsolutepn\x01\xff";
  int ok = 0, refused = 0;
  for (int trial = 0; trial < 4000; ++trial) {
    std::string text = seeds[trial % 4];
    const int edits = 1 + int(gen() % 4);
    for (int e = 0; e < edits; ++e) {
      const std::size_t at = gen() % (text.size() + 1);
      switch (gen() % 3) {
        case 0: if (at < text.size()) text[at] = alphabet[gen() % alphabet.size()]; break;
        case 1: text.insert(at, 1, alphabet[gen() % alphabet.size()]); break;
        default: if (at < text.size()) text.erase(at, 1); break;
      }
    }
    try {
      const auto s = trial % 4 == 0 ? io::parse_pose_csv(text, "f.csv") : io::parse_pose_json(text, "f.json");
      CHECK((s.size() >= 1 && s.y.size() == s.size() && s.yaw.size() == s.size()));
      for (std::size_t i = 0; i < s.size(); ++i) CHECK((std::isfinite(s.x[i]) && std::isfinite(s.y[i]) && std::isfinite(s.yaw[i])));
      ++ok;
    } catch (const Error& e) {
      CHECK(std::string(e.what()).find("f.") == 0);  // names the file first
      ++refused;
    }
  }
  MESSAGE("corrupted pose files: ", ok, " parsed, ", refused, " refused");
  CHECK(ok > 0);
  CHECK(refused > 0);
}
