// Does the bundled model (models/small-synthetic, docs/training.md) beat the trivial baselines on
// its held-out demo clip? `epona eval` runs in-process on the clip alone at the documented
// settings (100 steps, horizons 1..5, seed 0; docs/evaluation.md, "How") and the test reads its
// JSON report:
//   video:    the mean PSNR over horizons 1..5 of the model's rollout beats repeat-last's;
//   planning: the model's L2 at 3 s beats constant velocity's.
// docs/evaluation.md ("What it shows") gives the same comparison on 200 held-out clips. Only the
// two means are asserted, never a single horizon: on this clip the first bundled model lost at h4 (21.4 vs
// 23.1 dB), and the per-horizon order is not what the model promises. Margins measured (Release,
// seed 0): the first bundled model PSNR 23.47 vs 22.50 dB, L2 at 3 s 5.26 vs 6.96 m; run 2's
// 24.34 vs 22.50 dB and 1.01 vs 6.96 m; run 4's (bundled since 2026-11-28) 24.49 vs 22.50 dB and
// 0.16 m (its eight-plan mean; one plan 0.84 m) vs 6.96 m.
#include <doctest/doctest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "../apps/cli_testing.hpp"
#include "../temp_dir.hpp"
#include "bundled_model.hpp"

using namespace epona;
using epona::test::kBundledModel;
using nlohmann::json;

namespace {

double mean_of(const json& values) {
  const std::vector<double> v = values.get<std::vector<double>>();
  REQUIRE(v.size() == 5);
  return std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
}

}  // namespace

TEST_CASE("demo clip: the bundled model beats repeat-last on video and constant velocity on planning") {
  const test::TempDir t("epona_quality_demo");
  const std::string report = t / "eval.json";
  const test::CliResult r = test::cli({"eval", "--clips", kBundledModel + "/demo", "--weights", kBundledModel + "/weights_world.safetensors",
                                       "--dcae", kBundledModel + "/weights_dcae.safetensors", "--config", kBundledModel + "/configs.json",
                                       "--steps", "100", "--horizon", "5", "--seed", "0", "--json", report, "-q"});
  REQUIRE_MESSAGE(r.rc == 0, r.out, r.err);
  std::ifstream in(report);
  const json j = json::parse(in);
  REQUIRE(j.at("clips") == 1);

  const double model_psnr = mean_of(j.at("model").at("psnr")), repeat_psnr = mean_of(j.at("repeat_last").at("psnr"));
  const double model_l2 = j.at("model").at("l2_3s"), cv_l2 = j.at("constant_velocity").at("l2_3s");
  MESSAGE("mean PSNR h1..h5: model ", model_psnr, " dB, repeat-last ", repeat_psnr, " dB; L2 at 3 s: model ", model_l2,
          " m, constant velocity ", cv_l2, " m");
  CHECK(model_psnr > repeat_psnr);
  CHECK(model_l2 < cv_l2);
}

// The one translation unit of this test program that compiles stb.
#include "epona/io/stb_implementation.hpp"
