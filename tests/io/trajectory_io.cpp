// Tests for epona/domain/trajectory_io.hpp: planned trajectories written as CSV/JSON/.npy read back
// bit-exactly (shortest round-trip decimals), the files' layout, per-step actions for a replay,
// and malformed files ending in errors that name the file and line/step.
#include <doctest/doctest.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>

#include "epona/domain/trajectory_io.hpp"
#include "../temp_dir.hpp"

using namespace epona;
using epona::test::TempDir;
namespace fs = std::filesystem;

namespace {

Tensor<float> random_trajectory(std::int64_t S, std::int64_t W, unsigned seed) {
  std::mt19937 gen(seed);
  std::normal_distribution<float> n(0, 3);
  Tensor<float> t({S, W, 3});
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = n(gen);
  return t;
}

bool bit_equal(const Tensor<float>& a, const Tensor<float>& b) {
  return a.shape() == b.shape() && std::memcmp(a.data(), b.data(), a.nbytes()) == 0;
}

Tensor<float> trajectory_csv(const std::string& text) { return io::parse_trajectory_csv(text, "t.csv"); }
Tensor<float> trajectory_json(const std::string& text) { return io::parse_trajectory_json(text, "t.json"); }

}  // namespace

TEST_CASE("trajectories round-trip bit-exactly through CSV, JSON and .npy") {
  TempDir dir;
  auto t = random_trajectory(3, 15, 1);
  // awkward values: signed zero, subnormal, extremes of fp32, values near decimal ties
  const float special[] = {-0.0f, 1e-45f, std::numeric_limits<float>::max(), -std::numeric_limits<float>::min(),
                           0.1f, 1.0f / 3.0f, 16777217.0f, 8.015625f};
  std::copy(std::begin(special), std::end(special), t.data());
  for (const std::string name : {"plan.csv", "plan.json", "plan.npy"}) {
    CAPTURE(name);
    io::write_trajectory(dir.path / name, t);
    CHECK(bit_equal(io::read_trajectory(dir.path / name), t));
  }
  // Many random floats of every magnitude through the decimal formats.
  std::mt19937 gen(2);
  Tensor<float> r({1000, 15, 3});
  for (std::int64_t i = 0; i < r.numel(); ++i) {
    std::uint32_t bits = gen();
    std::memcpy(&r.data()[i], &bits, 4);
    if (!std::isfinite(r.data()[i])) r.data()[i] = float(i);
  }
  CHECK(bit_equal(trajectory_csv(io::trajectory_to_csv(r)), r));
  CHECK(bit_equal(trajectory_json(io::trajectory_to_json(r)), r));
}

TEST_CASE("a single (W, 3) trajectory is one step; the files say what the numbers mean") {
  Tensor<float> w({2, 3});
  for (int i = 0; i < 6; ++i) w.data()[i] = 0.5f * float(i);
  const std::string c = io::trajectory_to_csv(w);
  CHECK(c.find("x metres forward, y metres left, yaw degrees (left turn > 0)") != std::string::npos);
  CHECK(c.find("step,waypoint,x,y,yaw\n0,0,0,0.5,1\n0,1,1.5,2,2.5\n") != std::string::npos);
  const std::string j = io::trajectory_to_json(w);
  CHECK(j.find("\"format\": \"epona-trajectory\"") != std::string::npos);
  CHECK(j.find("[[0, 0.5, 1], [1.5, 2, 2.5]]") != std::string::npos);
  const auto back = trajectory_json(j);
  CHECK(back.shape() == Shape{1, 2, 3});
  CHECK(back.at(0, 1, 2) == 2.5f);
  // Hand-written files: spaces, comments, CRLF, no format/units keys.
  const auto h = trajectory_csv("# mine\r\nstep, waypoint, x, y, yaw\r\n0, 0, 1, 2, 3 # first\r\n1,0,4,5,6\r\n");
  CHECK(h.shape() == Shape{2, 1, 3});
  CHECK(h.at(1, 0, 0) == 4.f);
  CHECK(trajectory_json(R"({"steps": [[[1, 2, 3]]]})").at(0, 0, 2) == 3.f);
}

TEST_CASE("a plan written with its hypotheses reads back as the plan; the fan's keys are in the file") {
  TempDir dir;
  const auto fan = random_trajectory(4, 15, 3);
  const Tensor<float> chosen = fan[2].clone();
  std::vector<double> spread(15, 0.25);
  io::write_trajectory_json(dir.path / "trajectory.json", chosen, {fan, "medoid", 2, spread});
  const auto back = io::read_trajectory(dir.path / "trajectory.json");
  CHECK(bit_equal(back, chosen.reshape({1, 15, 3})));
  const auto j = nlohmann::json::parse(std::ifstream(dir.path / "trajectory.json"));
  CHECK(j["choice"]["rule"] == "medoid");
  CHECK(j["choice"]["index"] == 2);
  CHECK(j["spread_m"].size() == 15);
  REQUIRE(j["hypotheses"].size() == 4);
  CHECK(j["hypotheses"][3][14][1].get<float>() == fan.at(3, 14, 1));
  // The mean picks no hypothesis.
  const std::string mean = io::trajectory_to_json(chosen, nullptr);
  io::TrajectoryFan no_index{fan, "mean", std::nullopt, spread};
  CHECK(io::trajectory_to_json(chosen, &no_index).find("\"index\": null") != std::string::npos);
  CHECK(mean.find("hypotheses") == std::string::npos);
}

TEST_CASE("per-step actions: first waypoints of a planned trajectory, or the rows of a pose file") {
  TempDir dir;
  const auto t = random_trajectory(4, 15, 3);
  for (const std::string name : {"plan.csv", "plan.json", "plan.npy"}) {
    CAPTURE(name);
    io::write_trajectory(dir.path / name, t);
    const auto a = io::read_actions(dir.path / name);
    REQUIRE(a.size() == 4);
    for (std::int64_t s = 0; s < 4; ++s) {
      CHECK(a.x[s] == t.at(s, 0, 0));
      CHECK(a.y[s] == t.at(s, 0, 1));
      CHECK(a.yaw[s] == t.at(s, 0, 2));
    }
  }
  const auto rows = io::read_actions(dir.write("actions.csv", "# per-frame\nx,y,yaw\n2,0,1\n2.5,0.1,-1\n"));
  REQUIRE(rows.size() == 2);
  CHECK(rows.x[1] == 2.5f);
  CHECK(rows.yaw[1] == -1.f);
  const auto hand = io::read_actions(dir.write("hand.csv", "Step , waypoint,x,y,yaw\n0,0,1,2,3\n0,1,9,9,9\n"));
  REQUIRE(hand.size() == 1);
  CHECK(hand.x[0] == 1.f);
  CHECK(io::read_actions(dir.write("a.json", R"({"poses": [[1, 0, 0], [2, 0, 0]]})")).size() == 2);
  io::write_npy(dir.path / "rows.npy", random_trajectory(1, 5, 4).reshape({5, 3}));  // (N, 3) rows
  CHECK(io::read_actions(dir.path / "rows.npy").size() == 5);
}

TEST_CASE("malformed trajectory files name the file and line or step") {
  struct Case {
    std::string text, expect;
  };
  const Case csv_cases[] = {
      {"", "t.csv: empty file (expected the header 'step,waypoint,x,y,yaw')"},
      {"# nothing\n", "t.csv: empty file"},
      {"step,waypoint,x,y,yaw\n", "t.csv: no trajectory rows"},
      {"x,y,yaw\n1,2,3\n", "t.csv: line 1: expected the header 'step,waypoint,x,y,yaw', got 'x,y,yaw'"},
      {"step,waypoint,x,y,yaw\n0,0,1,2\n", "line 2: expected 5 values (step, waypoint, x, y, yaw), got 4"},
      {"step,waypoint,x,y,yaw\n0,-1,1,2,3\n", "line 2: step and waypoint must be non-negative integers"},
      {"step,waypoint,x,y,yaw\n0,0.5,1,2,3\n", "line 2: step and waypoint must be non-negative integers"},
      {"step,waypoint,x,y,yaw\n0,1,1,2,3\n", "line 2: expected step 0, waypoint 0"},
      {"step,waypoint,x,y,yaw\n0,0,1,2,3\n0,2,1,2,3\n", "line 3: expected step 0, waypoint 1"},
      {"step,waypoint,x,y,yaw\n0,0,1,2,3\n2,0,1,2,3\n", "line 3: expected step 1, waypoint 0"},
      {"step,waypoint,x,y,yaw\n0,0,1,2,3\n0,1,1,2,3\n1,0,1,2,3\n",
       "t.csv: at the end: step 1 has 1 waypoints, the steps before it have 2"},
      {"step,waypoint,x,y,yaw\n0,0,1,2,3\n1,0,1,2,3\n1,1,1,2,3\n", "line 4: step 1 has more waypoints than the 1 of"},
      {"step,waypoint,x,y,yaw\n0,0,1,2,3\n0,1,1,2,3\n1,0,1,2,3\n2,0,1,2,3\n",
       "line 5: step 1 has 1 waypoints, the steps before it have 2"},
      {"step,waypoint,x,y,yaw\n0,0,1,two,3\n", "line 2: y = 'two' is not a number"},
      {"step,waypoint,x,y,yaw\n0,0,1,2,nan\n", "line 2: yaw = nan is not a finite number"},
  };
  for (const auto& c : csv_cases) {
    CAPTURE(c.text);
    CHECK_THROWS_WITH_AS(trajectory_csv(c.text), doctest::Contains(c.expect.c_str()), Error);
  }
  const Case json_cases[] = {
      {"[", "t.json: invalid JSON"},
      {"[[[1, 2, 3]]]", "t.json: expected an object with \"steps\""},
      {R"({"steps": [[[1, 2, 3]]], "extra": 1})", "t.json: unexpected key 'extra'"},
      {R"({"format": "other", "steps": [[[1, 2, 3]]]})", "\"format\" is \"other\", expected \"epona-trajectory\""},
      {R"({"steps": 3})", "\"steps\" must be a list"},
      {R"({"steps": []})", "t.json: no trajectory rows"},
      {R"({"steps": [[]]})", "t.json: step 0 must be a non-empty list of waypoints"},
      {R"({"steps": [[[1, 2, 3]], [[1, 2]]]})", "t.json: step 1, waypoint 0: expected [x, y, yaw], got a list of 2 value(s)"},
      {R"({"steps": [[[1, 2, 3], [1, 2, 3]], [[1, 2, 3]]]})", "step 1 has 1 waypoints, the steps before it have 2"},
      {R"({"steps": [[[1, 2, 3]], [[1, 2, 3], [1, 2, 3]]]})", "step 1, waypoint 1: step 1 has more waypoints than the 1"},
      {R"({"steps": [[[1, true, 3]]]})", "step 0, waypoint 0: y must be a number, got true"},
  };
  for (const auto& c : json_cases) {
    CAPTURE(c.text);
    CHECK_THROWS_WITH_AS(trajectory_json(c.text), doctest::Contains(c.expect.c_str()), Error);
  }
}

TEST_CASE("writing refuses what it could not read back") {
  TempDir dir;
  auto t = random_trajectory(2, 15, 5);
  t.at(1, 7, 2) = std::numeric_limits<float>::infinity();
  CHECK_THROWS_WITH_AS(io::write_trajectory(dir.path / "p.csv", t), doctest::Contains("step 1, waypoint 7: yaw = inf"),
                       Error);
  CHECK_THROWS_WITH_AS(io::write_trajectory(dir.path / "p.csv", Tensor<float>::zeros({15, 2})),
                       doctest::Contains("(W, 3) or (S, W, 3)"), Error);
  CHECK_THROWS_WITH_AS(io::write_trajectory(dir.path / "p.csv", Tensor<float>::zeros({1, 0, 3})),
                       doctest::Contains("W >= 1"), Error);
  CHECK_THROWS_WITH_AS(io::write_trajectory(dir.path / "p.pt", random_trajectory(1, 2, 0)),
                       doctest::Contains("unknown trajectory file type '.pt'"), Error);
  CHECK(fs::is_empty(dir.path));  // nothing half-written
  CHECK_THROWS_WITH_AS(io::read_trajectory(dir.path / "absent.json"), doctest::Contains("absent.json: not found"), Error);
  io::write_npy(dir.path / "bad.npy", Tensor<float>::zeros({2, 15, 4}));
  CHECK_THROWS_WITH_AS(io::read_trajectory(dir.path / "bad.npy"), doctest::Contains("bad.npy: a trajectory has shape"),
                       Error);
}

TEST_CASE("random corruption of trajectory files: a (S, W, 3) tensor or an epona::Error, nothing else") {
  const auto t = random_trajectory(2, 3, 9);
  const std::string seeds[] = {io::trajectory_to_csv(t), io::trajectory_to_json(t)};
  std::mt19937 gen(12);
  const std::string alphabet = "0123456789.,-+eE#\n \t[]{}\":stepwaypointxy\x01\xff";
  int ok = 0, refused = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    std::string text = seeds[trial % 2];
    for (int e = 0, edits = 1 + int(gen() % 3); e < edits; ++e) {
      const std::size_t at = gen() % text.size();
      if (gen() % 2) text[at] = alphabet[gen() % alphabet.size()];
      else text.erase(at, 1);
    }
    try {
      const auto r = trial % 2 ? trajectory_json(text) : trajectory_csv(text);
      CHECK((r.dim() == 3 && r.size(0) >= 1 && r.size(1) >= 1 && r.size(2) == 3));
      ++ok;
    } catch (const Error& e) {
      CHECK(std::string(e.what()).find("t.") == 0);
      ++refused;
    }
  }
  MESSAGE("corrupted trajectory files: ", ok, " parsed, ", refused, " refused");
  CHECK(ok > 0);
  CHECK(refused > 0);
}
