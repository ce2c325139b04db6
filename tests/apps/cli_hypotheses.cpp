// `epona plan --hypotheses K` and `eval --hypotheses K` (apps/epona/cmd_plan.hpp, cmd_eval.hpp) on
// the bundled demo model, in-process: trajectory.json holds all K with the choice and spread, its
// plan is the chosen hypothesis (medoid) or their mean, hypothesis 0 is the plan without the
// option, plan.png still reads back; eval reports the chosen plan, the best of K and the spread,
// and bad values are refused naming the option.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "../temp_dir.hpp"
#include "../../apps/epona/bundled_model.hpp"
#include "cli_testing.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::read_json;
using epona::test::TempDir;
using nlohmann::json;
using test::cli;
using test::has;

TEST_CASE("plan --hypotheses 3: all three in trajectory.json, the medoid written as the plan") {
  TempDir t;
  const auto r = cli({"plan", "--hypotheses", "3", "--seed", "7", "--steps", "4", "--out", t / "k3"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "3 hypotheses, the medoid chosen (hypothesis "));
  const json j = read_json(t.path / "k3/trajectory.json");
  REQUIRE(j["hypotheses"].size() == 3);
  CHECK(j["choice"]["rule"] == "medoid");
  const int chosen = j["choice"]["index"].get<int>();
  CHECK(j["steps"][0] == j["hypotheses"][chosen]);
  CHECK(j["spread_m"].size() == j["steps"][0].size());
  CHECK(j["spread_m"].back().get<double>() > 0);
  CHECK(j["hypotheses"][0] != j["hypotheses"][1]);
  // trajectory.csv is the chosen plan; every reader takes the JSON as that plan.
  const Tensor<float> csv = io::read_trajectory(t.path / "k3/trajectory.csv");
  const Tensor<float> from_json = io::read_trajectory(t.path / "k3/trajectory.json");
  REQUIRE(csv.numel() == from_json.numel());
  for (std::int64_t i = 0; i < csv.numel(); ++i) CHECK(csv.data()[i] == from_json.data()[i]);
  CHECK(fs::file_size(t.path / "k3/plan.png") > 0);

  // Hypothesis 0 is the single plan (--hypotheses 1), up to rounding: the GEMMs block K rows other
  // than one.
  REQUIRE(cli({"plan", "--hypotheses", "1", "--seed", "7", "--steps", "4", "--out", t / "k1", "-q"}).rc == 0);
  const json alone = read_json(t.path / "k1/trajectory.json");
  CHECK(!alone.contains("hypotheses"));
  double scale = 0, worst = 0;
  for (std::size_t w = 0; w < alone["steps"][0].size(); ++w)
    for (int c = 0; c < 3; ++c) {
      const double a = alone["steps"][0][w][c].get<double>(), b = j["hypotheses"][0][w][c].get<double>();
      scale = std::max(scale, std::abs(b)), worst = std::max(worst, std::abs(a - b));
    }
  CHECK(worst <= 1e-6 * scale);
}

TEST_CASE("plan --choose mean: the waypoint-wise mean, no index") {
  TempDir t;
  REQUIRE(cli({"plan", "--hypotheses", "4", "--choose", "mean", "--steps", "3", "--out", t / "m", "-q"}).rc == 0);
  const json j = read_json(t.path / "m/trajectory.json");
  CHECK(j["choice"]["index"].is_null());
  const auto& h = j["hypotheses"];
  for (std::size_t w = 0; w < j["steps"][0].size(); ++w)
    for (int c = 0; c < 3; ++c) {
      double sum = 0;
      for (const auto& hyp : h) sum += hyp[w][c].get<double>();
      CHECK(j["steps"][0][w][c].get<double>() == doctest::Approx(sum / 4).epsilon(1e-5));
    }
}

TEST_CASE("without the flags, the model's recommended rule applies (configs.json planner: 8, mean)") {
  TempDir t;
  // The demo model's configuration plus the planner block the bundled trained model carries.
  json configs = read_json(fs::path(app::demo_model_dir()) / "configs.json");
  configs["planner"] = {{"hypotheses", 8}, {"choose", "mean"}};
  std::ofstream(t / "configs.json") << configs.dump();
  const std::string config = t / "configs.json";
  const auto plan = [&](std::vector<std::string> extra, const std::string& out) {
    std::vector<std::string> args{"plan", "--config", config, "--seed", "5", "--steps", "3", "--out", t / out};
    args.insert(args.end(), extra.begin(), extra.end());
    return cli(args);
  };
  const auto r = plan({}, "d");
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.err + r.out, "8 hypotheses, the mean chosen (the model's recommended rule"));
  const json d = read_json(t.path / "d/trajectory.json");
  REQUIRE(d["hypotheses"].size() == 8);
  CHECK(d["choice"]["rule"] == "mean");
  // The same as asking for it; the command line overrides either part.
  REQUIRE(plan({"--hypotheses", "8", "--choose", "mean", "-q"}, "e").rc == 0);
  CHECK(read_json(t.path / "e/trajectory.json")["steps"] == d["steps"]);
  REQUIRE(plan({"--choose", "medoid", "-q"}, "f").rc == 0);
  const json f = read_json(t.path / "f/trajectory.json");
  CHECK(f["hypotheses"].size() == 8);
  CHECK(f["choice"]["rule"] == "medoid");
  REQUIRE(plan({"--hypotheses", "1", "-q"}, "g").rc == 0);
  CHECK(!read_json(t.path / "g/trajectory.json").contains("hypotheses"));
  // Without the block (the demo model's own configuration), one plan.
  REQUIRE(cli({"plan", "--seed", "5", "--steps", "3", "--out", t / "h", "-q"}).rc == 0);
  CHECK(!read_json(t.path / "h/trajectory.json").contains("hypotheses"));
}

TEST_CASE("bad --hypotheses and --choose are refused, naming the option") {
  TempDir t;
  for (const char* k : {"0", "-2", "1025", "many"}) {
    const auto r = cli({"plan", "--hypotheses", k, "--out", t / "x", "-q"});
    CHECK(r.rc == 1);
    CHECK(has(r.err, "--hypotheses"));
  }
  const auto r = cli({"plan", "--hypotheses", "2", "--choose", "best", "--out", t / "x", "-q"});
  CHECK(r.rc == 1);
  CHECK(has(r.err, "--choose"));
}

// stb_image / stb_image_write, compiled once per test program.
#include "epona/io/stb_implementation.hpp"
