// Tests of the synthetic driving world (include/epona/synth/) and `epona synth`
// (apps/epona/cmd_synth.hpp): byte-identical reruns, clip k independent of the clip count and the
// thread count, motions finite and within Epona's ranges, future motions continuing the history
// (checked against the absolute poses of --format npy), boxes in the last history frame's ego
// frame, variety over a dozen drives (curves both ways, slow and fast drives, lane changes,
// traffic), plausible pictures, a frame rendered from another pose, and clear errors for bad
// options. Small sizes keep it fast.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "../apps/cli_testing.hpp"
#include "../temp_dir.hpp"
#include "epona/io/image.hpp"
#include "epona/io/npy.hpp"
#include "epona/synth/scenario.hpp"

namespace fs = std::filesystem;
using namespace epona;

namespace {

using test::cli;
using test::TempDir;

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// Every file under `dir` (relative name -> bytes), in name order.
std::vector<std::pair<std::string, std::string>> tree(const fs::path& dir) {
  std::vector<std::pair<std::string, std::string>> files;
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (e.is_regular_file()) files.emplace_back(fs::relative(e.path(), dir).string(), slurp(e.path()));
  std::sort(files.begin(), files.end());
  return files;
}

std::vector<std::string> synth_args(const fs::path& out, const std::string& seed, const std::string& clips) {
  return {"synth", "--seed", seed, "--clips", clips, "--frames", "3", "--future", "2", "--size", "64x128",
          "--quiet", "--out", out.string()};
}

std::vector<std::array<double, 3>> read_csv(const fs::path& p) {
  std::istringstream in(slurp(p));
  std::string line;
  std::getline(in, line);
  CHECK(line == "x,y,yaw");
  std::vector<std::array<double, 3>> rows;
  while (std::getline(in, line)) {
    std::array<double, 3> r{};
    char c1, c2;
    std::istringstream ls(line);
    ls >> r[0] >> c1 >> r[1] >> c2 >> r[2];
    REQUIRE(!ls.fail());
    rows.push_back(r);
  }
  return rows;
}

}  // namespace

TEST_CASE("synth: same seed, same bytes; clip k independent of the clip count; seeds differ") {
  TempDir a, b, c, d;
  REQUIRE(cli(synth_args(a.path, "5", "3")).rc == 0);
  REQUIRE(cli(synth_args(b.path, "5", "3")).rc == 0);
  REQUIRE(cli(synth_args(c.path, "5", "1")).rc == 0);
  REQUIRE(cli(synth_args(d.path, "6", "1")).rc == 0);
  const auto ta = tree(a.path), tb = tree(b.path);
  REQUIRE(ta.size() == tb.size());
  for (std::size_t i = 0; i < ta.size(); ++i) {
    CHECK(ta[i].first == tb[i].first);
    CHECK(ta[i].second == tb[i].second);
  }
  const auto c0 = tree(c.path / "clip_0000"), a0 = tree(a.path / "clip_0000");
  REQUIRE(c0.size() == a0.size());
  CHECK(c0.size() == 3 + 2 + 4);  // frames, future frames, two CSVs, boxes, scene
  for (std::size_t i = 0; i < c0.size(); ++i) CHECK(c0[i].second == a0[i].second);
  CHECK(slurp(a.path / "clip_0000" / "poses.csv") != slurp(a.path / "clip_0001" / "poses.csv"));
  CHECK(slurp(d.path / "clip_0000" / "poses.csv") != slurp(c.path / "clip_0000" / "poses.csv"));
  CHECK(read_csv(c.path / "clip_0000" / "poses.csv").size() == 3);
  CHECK(read_csv(c.path / "clip_0000" / "future_poses.csv").size() == 15);
  const std::string clips = slurp(c.path / "clips.json");
  CHECK(clips.find("\"format\":\"epona-synth\",\"version\":1,\"seed\":5,\"clips\":1,\"frames\":3,\"future\":2,"
                   "\"future_poses\":15,\"size\":[64,128],\"fps\":5") != std::string::npos);
  const io::Image img = io::read_image((c.path / "clip_0000" / "frames" / "frame_02.png").string());
  CHECK(img.height == 64);
  CHECK(img.width == 128);
}

TEST_CASE("synth: the picture does not depend on the thread count") {
  const synth::Scenario sc(11, 0, 3);
  synth::RenderOptions o;
  o.camera.height = 64, o.camera.width = 128, o.threads = 1;
  const io::Image one = sc.render(2, o);
  o.threads = 3;
  CHECK(sc.render(2, o).rgb == one.rgb);
}

TEST_CASE("synth: a frame's world rendered from another pose") {
  const synth::Scenario sc(11, 0, 3);
  synth::RenderOptions o;
  o.camera.height = 64, o.camera.width = 128;
  synth::Pose2 ego = sc.frames()[2].ego;
  CHECK(sc.render(2, o, ego).rgb == sc.render(2, o).rgb);  // the recorded pose: the frame itself
  ego.yaw += synth::rad(5);
  CHECK(sc.render(2, o, ego).rgb != sc.render(2, o).rgb);
}

TEST_CASE("synth: npy layout; future motions continue the history; boxes in the last history frame") {
  TempDir t;
  const test::CliResult r = cli({"synth", "--seed", "2", "--clips", "2", "--frames", "4", "--future", "16", "--size", "32x64",
                        "--supersample", "1", "--format", "npy", "--quiet", "--out", t.path.string()});
  REQUIRE_MESSAGE(r.rc == 0, r.err);
  for (const char* clip : {"clip_0000", "clip_0001"}) {
    const fs::path dir = t.path / clip;
    CHECK(!fs::exists(dir / "frames"));
    const auto frames = io::read_whole_file(dir / "frames.npy");
    const std::string fh(reinterpret_cast<const char*>(frames.data()), 128);
    CHECK(fh.find("'descr': '|u1'") != std::string::npos);
    CHECK(fh.find("'shape': (20, 32, 64, 3)") != std::string::npos);
    const auto abs = io::read_npy<double>(dir / "poses_abs.npy");
    REQUIRE(abs.values.shape() == Shape{4 + 16, 3});
    auto rows = read_csv(dir / "poses.csv");
    const auto future = read_csv(dir / "future_poses.csv");
    CHECK(rows.size() == 4);
    CHECK(future.size() == 16);
    rows.insert(rows.end(), future.begin(), future.end());
    for (std::size_t i = 1; i < rows.size(); ++i) {
      const synth::Pose2 p0{abs.values.at(i - 1, 0), abs.values.at(i - 1, 1), abs.values.at(i - 1, 2)};
      const synth::Pose2 p1{abs.values.at(i, 0), abs.values.at(i, 1), abs.values.at(i, 2)};
      const synth::Motion m = synth::motion_between(p0, p1);
      CHECK(std::abs(m.x - rows[i][0]) < 1e-4);
      CHECK(std::abs(m.y - rows[i][1]) < 1e-4);
      CHECK(std::abs(m.yaw_deg - rows[i][2]) < 1e-3);
    }
    const std::string boxes = slurp(dir / "boxes.json");
    CHECK(boxes.rfind("{\"frame_of\":\"last history frame\",\"ego\":{\"length\":", 0) == 0);
    CHECK(std::count(boxes.begin(), boxes.end(), '\n') == 4 + 16 + 2);  // one line per frame list
  }
}

TEST_CASE("synth: motions in Epona's range, lead vehicles ahead, and variety over a dozen drives") {
  bool left = false, right = false, slow = false, fast = false, vehicles = false;
  int lane_changes = 0, leads = 0;
  for (std::uint64_t k = 0; k < 12; ++k) {
    const synth::Scenario sc(7, k, 100);
    double yaw = 0;
    for (std::int64_t i = 0; i < sc.size(); ++i) {
      const synth::Motion m = sc.motion(i);
      REQUIRE(std::isfinite(m.x));
      REQUIRE(std::isfinite(m.y));
      REQUIRE(std::isfinite(m.yaw_deg));
      CHECK(m.x >= 0);
      CHECK(m.x < 8);
      CHECK(std::abs(m.y) < 0.5);
      CHECK(std::abs(m.yaw_deg) < 8);
      yaw += m.yaw_deg;
      const double v = sc.frames()[std::size_t(i)].speed;
      slow |= v < 5, fast |= v > 20;
    }
    left |= yaw > 10, right |= yaw < -10;
    lane_changes += sc.lane_changes();
    // The nearest vehicle ahead in the ego's lane lies ahead (x > 0) and near the centre line.
    const synth::FrameState& f = sc.frames().back();
    vehicles |= !f.vehicles.empty();
    const synth::Road& road = sc.road();
    double best = 1e9;
    synth::Motion lead{};
    for (const synth::VehicleBox& v : f.vehicles) {
      std::int64_t hint = static_cast<std::int64_t>(f.s);
      double s, d;
      road.project(v.pose.x, v.pose.y, hint, s, d);
      if (std::abs(d - f.d) < 1.0 && s > f.s + 3 && s - f.s < best) best = s - f.s, lead = synth::motion_between(f.ego, v.pose);
    }
    if (best < 60) {
      ++leads;
      CHECK(lead.x > 3);
      CHECK(std::abs(lead.y) < 2 + lead.x * lead.x / 80);  // a curve of radius >= 40 m bends the lane away
    }
  }
  CHECK(left);
  CHECK(right);
  CHECK(slow);
  CHECK(fast);
  CHECK(lane_changes >= 1);
  CHECK(vehicles);
  CHECK(leads >= 1);
}

// The exploring driver (training data that teaches action following): its steering impulses turn
// the ego by several degrees within a frame where the natural driver's heading changes smoothly,
// its motions stay inside the range Epona's pose tokenizer covers (|yaw| < 8 deg, 0 <= x < 8 m),
// and reruns are identical.
TEST_CASE("synth: the exploring driver swerves at random moments, within Epona's ranges") {
  auto jumps = [](const synth::Scenario& sc, double& max_yaw) {
    int n = 0;
    for (std::int64_t i = 1; i < sc.size(); ++i) {
      const synth::Motion m = sc.motion(i), prev = sc.motion(i - 1);
      REQUIRE(std::isfinite(m.yaw_deg));
      CHECK(m.x >= 0);
      CHECK(m.x < 8);
      CHECK(std::abs(m.y) < 0.5);
      CHECK(std::abs(m.yaw_deg) < 8);
      max_yaw = std::max(max_yaw, std::abs(m.yaw_deg));
      n += std::abs(m.yaw_deg - prev.yaw_deg) > 1.5;
    }
    return n;
  };
  int natural_jumps = 0, exploring_jumps = 0, impulses = 0;
  double natural_max = 0, exploring_max = 0;
  for (std::uint64_t k = 0; k < 12; ++k) {
    const synth::Scenario natural(7, k, 100), exploring(7, k, 100, synth::Exploration{});
    CHECK_FALSE(natural.exploring());
    CHECK(exploring.exploring());
    natural_jumps += jumps(natural, natural_max);
    exploring_jumps += jumps(exploring, exploring_max);
    impulses += exploring.impulses();
  }
  CHECK(impulses >= 12 * 20 / 3);  // 20 s per drive, one impulse per 2 s on average
  CHECK(natural_jumps <= 12);
  CHECK(exploring_jumps >= 5 * std::max(natural_jumps, 10));
  CHECK(exploring_max > 4);  // the 5-degree turns of eval --control are in the training range
  const synth::Scenario a(3, 1, 40, synth::Exploration{}), b(3, 1, 40, synth::Exploration{});
  for (std::int64_t i = 0; i < a.size(); ++i) CHECK(a.motion(i).yaw_deg == b.motion(i).yaw_deg);

  TempDir tmp("synth_explore");
  auto args = synth_args(tmp.path / "x", "4", "1");
  args.push_back("--explore");
  REQUIRE(cli(args).rc == 0);
  CHECK(slurp(tmp.path / "x" / "clips.json").find("\"exploring_driver\":true") != std::string::npos);
  CHECK(slurp(tmp.path / "x" / "clip_0000" / "scene.json").find("\"exploring_driver\":{\"impulses\":") != std::string::npos);
  REQUIRE(cli(synth_args(tmp.path / "n", "4", "1")).rc == 0);
  CHECK(slurp(tmp.path / "n" / "clip_0000" / "scene.json").find("exploring") == std::string::npos);
}

TEST_CASE("synth: frames look like a road scene") {
  for (std::uint64_t k = 0; k < 3; ++k) {
    const synth::Scenario sc(1, k, 2);
    synth::RenderOptions o;
    o.camera.height = 96, o.camera.width = 192;
    const io::Image img = sc.render(1, o);
    auto mean = [&](int y0, int y1, int x0, int x1) {
      double s = 0;
      for (int y = y0; y < y1; ++y)
        for (int x = x0; x < x1; ++x) s += img.at(y, x, 0) + img.at(y, x, 1) + img.at(y, x, 2);
      return s / (3.0 * (y1 - y0) * (x1 - x0));
    };
    const double sky = mean(0, 8, 0, 192), road = mean(88, 96, 64, 128);
    CHECK_MESSAGE(road + 20 < sky, "clip ", k, ": road ", road, " sky ", sky);
    // The horizon (0.42 of the height): brightness drops across it at the centre columns.
    CHECK(mean(30, 38, 80, 112) > mean(60, 68, 80, 112));
    double var = 0, m = mean(0, 96, 0, 192);
    for (std::uint8_t v : img.rgb) var += (v - m) * (v - m);
    CHECK(std::sqrt(var / double(img.rgb.size())) > 15);
  }
}

TEST_CASE("synth: bad options give clear errors") {
  TempDir t;
  const std::string out = t.path.string();
  const std::vector<std::pair<std::vector<std::string>, std::string>> cases = {
      {{"--clips", "0"}, "--clips must be in [1, 100000]"},
      {{"--clips", "1000001"}, "--clips must be in [1, 100000]"},
      {{"--frames", "0"}, "--frames must be in [1, 10000]"},
      {{"--frames", "ten"}, "--frames needs an integer"},
      {{"--future", "-1"}, "--future must be in [0, 10000]"},
      {{"--size", "100x512"}, "multiples of 32"},
      {{"--size", "256"}, "--size must be HEIGHTxWIDTH"},
      {{"--size", "8192x512"}, "multiples of 32 in [32, 4096]"},
      {{"--format", "jpg"}, "--format must be one of png, npy"},
      {{"--supersample", "0"}, "--supersample must be in [1, 8]"},
      {{"--threads", "0"}, "--threads must be in [1, 1024]"},
      {{"--seed", "-3"}, "--seed must be at least 0"},
      {{"--format", "npy", "--frames", "10000", "--size", "4096x4096"}, "more than 16 GB"},
      {{"--bogus"}, "unknown option '--bogus'"},
  };
  for (const auto& [extra, message] : cases) {
    std::vector<std::string> args{"synth", "--out", out, "--quiet"};
    args.insert(args.end(), extra.begin(), extra.end());
    const test::CliResult r = cli(args);
    CHECK(r.rc == 1);
    CHECK_MESSAGE(r.err.find("epona: error: ") == 0, r.err);
    CHECK_MESSAGE(r.err.find(message) != std::string::npos, r.err);
  }
  CHECK(!fs::exists(t.path / "clips.json"));
  CHECK(cli({"synth", "--help"}).out.find("--supersample") != std::string::npos);
  CHECK(cli({"--help"}).out.find("synth") != std::string::npos);
}

// stb is compiled once per program, in exactly one translation unit.
#include "epona/io/stb_implementation.hpp"
