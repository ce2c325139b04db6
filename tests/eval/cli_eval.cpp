// Tests of `epona eval` (apps/epona/cmd_eval.hpp) run in-process through app::run on the bundled
// demo model (64x128, condition_frames 3): a hand-made clip set of two clips (demo frames, known
// motions, one with boxes.json), every required JSON key with finite values of the right
// lengths, the constant-velocity L2 and collision rates against a hand computation, --limit not
// changing a clip's result, collision_rate null without boxes, --control's block consistent with
// its per-clip shifts (and a clip folder alone read as a set of one), bad inputs failing with
// the clip and file named and no report written, and the sampling options: each DiT's solver and
// steps in "settings", the plan per clip, --save-frames, Euler by name equal to the default.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "../apps/cli_testing.hpp"
#include "../temp_dir.hpp"
#include "epona/io/image.hpp"
#include "epona/eval/image_metrics.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::read_json;
using epona::test::write_file;
using epona::test::TempDir;
using nlohmann::json;

namespace {

using test::cli;
using test::has;
using Result = test::CliResult;

io::Image demo_frame(int i) {
  return io::read_image(std::string(EPONA_TEST_DATA_DIR) + "/demo/frame_0" + std::to_string(i) + ".png");
}

std::string rows(const std::string& row, int n) {
  std::string s = "x,y,yaw\n";
  for (int i = 0; i < n; ++i) s += row + "\n";
  return s;
}

// A clip: the 3 demo frames as history (last motion `last`), demo frames 1 and 2 as the two true
// future frames, 15 future motions of 1 m straight ahead.
void make_clip(const fs::path& dir, const std::string& last) {
  fs::create_directories(dir / "frames");
  fs::create_directories(dir / "future");
  for (int i = 0; i < 3; ++i) io::write_png((dir / "frames" / ("frame_0" + std::to_string(i) + ".png")).string(), demo_frame(i));
  for (int i = 0; i < 2; ++i) io::write_png((dir / "future" / ("frame_0" + std::to_string(i) + ".png")).string(), demo_frame(i + 1));
  write_file(dir / "poses.csv", "x,y,yaw\n2,0,0\n2,0,0\n" + last + "\n");
  write_file(dir / "future_poses.csv", rows("1,0,0", 15));
}

// Clip 0 goes 2 m a frame, clip 1 1 m left; a vehicle stands 10 m ahead in clip 0's future.
fs::path make_clip_set(const TempDir& t) {
  const fs::path set = t.path / "clips";
  make_clip(set / "clip_0000", "2,0,0");
  make_clip(set / "clip_0001", "0,1,0");
  std::string boxes = R"({"ego": {"length": 4, "width": 2}, "frames": [[], [], [])";
  for (int i = 0; i < 15; ++i) boxes += R"(, [{"x": 10, "y": 0, "yaw": 0, "length": 4, "width": 2}])";
  write_file(set / "clip_0000" / "boxes.json", boxes + "]}");
  return set;
}

std::vector<std::string> eval_args(const fs::path& clips, const fs::path& report) {
  return {"eval", "--clips", clips.string(), "--json", report.string(), "--steps", "2", "--horizon", "2", "-q"};
}

void check_number(const json& j, const std::string& key) {
  INFO(key);
  REQUIRE(j.contains(key));
  REQUIRE(j[key].is_number());
  CHECK(std::isfinite(j[key].get<double>()));
}

void check_series(const json& j, const std::string& key, std::size_t n) {
  INFO(key);
  REQUIRE(j.contains(key));
  REQUIRE(j[key].is_array());
  REQUIRE(j[key].size() == n);
  for (const auto& v : j[key]) CHECK((v.is_number() && std::isfinite(v.get<double>())));
}

const char* kPlanKeys[] = {"l2_1s", "l2_2s", "l2_3s", "l2_avg_1s", "l2_avg_2s", "l2_avg_3s",
                           "collision_rate", "collision_rate_1s", "collision_rate_2s", "collision_rate_3s"};

}  // namespace

TEST_CASE("eval on the demo model: every key, finite values, baselines by hand") {
  TempDir t;
  const fs::path set = make_clip_set(t), report = t.path / "eval.json";
  const Result r = cli(eval_args(set, report));
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "constant_velocity"));
  CHECK(has(r.out, "repeat_last"));
  const json j = read_json(report);
  CHECK(j["clips"] == 2);
  for (const char* who : {"model", "constant_velocity", "constant_turn"})
    for (const char* key : kPlanKeys) check_number(j[who], key);
  for (const char* who : {"model", "repeat_last", "autoencoder"}) {
    check_series(j[who], "psnr", 2);
    check_series(j[who], "ssim", 2);
  }
  CHECK(j["model"]["fid"].is_null());
  CHECK(j["fvd"].is_null());
  CHECK(has(j["notes"]["fid"].get<std::string>(), "not computed"));
  for (const char* key : {"steps", "seed", "horizon", "weights", "backend", "dtype"}) CHECK(j["settings"].contains(key));
  CHECK(j["settings"]["steps"] == 2);

  // Truth: waypoint n at (n + 1, 0). Constant velocity: clip 0 (2 (n + 1), 0), error n + 1;
  // clip 1 (0, n + 1), error sqrt 2 (n + 1). At 1/2/3 s (n = 4, 9, 14), averaged over the clips.
  const double k = (1 + std::sqrt(2.0)) / 2;
  const json& cv = j["constant_velocity"];
  CHECK(cv["l2_1s"].get<double>() == doctest::Approx(5 * k));
  CHECK(cv["l2_2s"].get<double>() == doctest::Approx(10 * k));
  CHECK(cv["l2_3s"].get<double>() == doctest::Approx(15 * k));
  CHECK(cv["l2_avg_1s"].get<double>() == doctest::Approx(3 * k));  // mean of 1..5
  CHECK(cv["l2_avg_3s"].get<double>() == doctest::Approx(8 * k));  // mean of 1..15
  CHECK(j["constant_turn"]["l2_3s"].get<double>() == doctest::Approx(15 * k));  // no turn: the same
  // Only clip 0 has boxes; its constant-velocity ego reaches the vehicle at 10 m by waypoint 4.
  CHECK(cv["collision_rate_1s"] == 1.0);
  CHECK(cv["collision_clips"] == 1);
  CHECK(j["ground_truth"]["collision_rate_1s"] == 0.0);  // 5 m at 1 s: clear
  CHECK(j["ground_truth"]["collision_rate_2s"] == 1.0);  // 10 m at 2 s: on it
  // The second true frame is the last history frame.
  CHECK(j["repeat_last"]["psnr"][1] == eval::kPsnrCap);
  CHECK(j["repeat_last"]["ssim"][1].get<double>() == doctest::Approx(1.0));

  REQUIRE(j["per_clip"].size() == 2);
  CHECK(j["per_clip"][0]["name"] == "clip_0000");
  CHECK(j["per_clip"][1]["psnr"].size() == 2);
  CHECK(j["per_clip"][0]["constant_velocity_l2_3s"].get<double>() == doctest::Approx(15));
  CHECK(j["per_clip"][1]["collision_3s"].is_null());

  // --limit 1: clip 0 alone, with the same seed and so the same result.
  const fs::path first = t.path / "first.json";
  auto args = eval_args(set, first);
  args.insert(args.end(), {"--limit", "1"});
  REQUIRE(cli(args).rc == 0);
  const json f = read_json(first);
  CHECK(f["clips"] == 1);
  CHECK(f["per_clip"][0] == j["per_clip"][0]);
}

TEST_CASE("eval: collision_rate is null without boxes; --no-video and --no-plan") {
  TempDir t;
  const fs::path set = make_clip_set(t), report = t.path / "eval.json";
  fs::remove(set / "clip_0000" / "boxes.json");
  auto args = eval_args(set, report);
  args.push_back("--no-video");
  REQUIRE(cli(args).rc == 0);
  json j = read_json(report);
  CHECK(j["model"]["collision_rate"].is_null());
  CHECK(j["model"]["l2_3s"].is_number());
  CHECK_FALSE(j["model"].contains("psnr"));
  args = eval_args(set, report);
  args.push_back("--no-plan");
  REQUIRE(cli(args).rc == 0);
  j = read_json(report);
  CHECK(j["model"]["l2_3s"].is_null());
  CHECK(j["model"]["psnr"].size() == 2);
}

TEST_CASE("eval --control: the report's control block agrees with its shifts; one clip folder alone is a set") {
  TempDir t;
  const fs::path set = make_clip_set(t), report = t.path / "eval.json";
  auto args = eval_args(set, report);
  args.insert(args.end(), {"--no-plan", "--no-video", "--control", "--control-yaw", "6", "--control-frames", "2"});
  const Result r = cli(args);
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "control (turn left vs right, yaw +-6 deg, 2 frame(s))"));
  const json j = read_json(report);
  const json& c = j["control"];
  CHECK(c["scenes"] == 2);
  CHECK(c["yaw_deg"] == 6);
  CHECK(c["frames"] == 2);
  CHECK(c["min_forward_m"] == 2.0);
  REQUIRE(c["per_clip"].size() == 2);
  int agree = 0;
  for (std::size_t i = 0; i < 2; ++i) {
    REQUIRE(c["per_clip"][i].is_number_integer());
    const auto shift = c["per_clip"][i].get<std::int64_t>();
    CHECK(std::abs(shift) <= 128 / 4);  // the search range: a quarter of the width
    CHECK(j["per_clip"][i]["control_shift_px"] == shift);
    agree += shift > 0;
  }
  CHECK(c["agree"] == agree);
  CHECK(c["agree_rate"].get<double>() == doctest::Approx(agree / 2.0));
  CHECK(c["shift_min_px"].get<std::int64_t>() <= c["shift_max_px"].get<std::int64_t>());
  CHECK(j["settings"]["control"] == true);
  CHECK(j["model"]["l2_3s"].is_null());

  // The clip folder alone: a set of one, clip 0, the same seed and so the same shift.
  const fs::path one = t.path / "one.json";
  auto single = eval_args(set / "clip_0000", one);
  single.insert(single.end(), {"--no-plan", "--no-video", "--control", "--control-yaw", "6", "--control-frames", "2"});
  REQUIRE(cli(single).rc == 0);
  const json o = read_json(one);
  CHECK(o["clips"] == 1);
  CHECK(o["control"]["per_clip"][0] == c["per_clip"][0]);
  // Without --control, no control block, and per-clip shifts are null.
  REQUIRE(cli(eval_args(set, one)).rc == 0);
  CHECK_FALSE(read_json(one).contains("control"));
  CHECK(read_json(one)["per_clip"][0]["control_shift_px"].is_null());
}

TEST_CASE("eval: bad inputs fail naming the clip and file, and write no report") {
  TempDir t;
  const fs::path set = make_clip_set(t), report = t.path / "eval.json";
  const auto fails_with = [&](const std::vector<std::string>& args, const std::string& part) {
    const Result r = cli(args);
    INFO(r.err);
    CHECK(r.rc == 1);
    CHECK(has(r.err, "epona: error:"));
    CHECK(has(r.err, part));
    CHECK_FALSE(fs::exists(report));
  };
  fails_with({"eval", "--json", report.string()}, "--clips DIR is needed");
  fails_with({"eval", "--clips", set.string()}, "--json FILE is needed");
  fails_with(eval_args(t.path / "nowhere", report), "no such folder");
  fails_with(eval_args(t.path, report), "no clips");
  fails_with({"eval", "--clips", set.string(), "--json", (t.path / "no" / "r.json").string()}, "does not exist");
  fails_with({"eval", "--clips", set.string(), "--json", report.string(), "--horizon", "3"}, "--horizon asks for 3");
  fails_with({"eval", "--clips", set.string(), "--json", report.string(), "--control", "--control-yaw", "8"},
             "--control-yaw must be in [1, 7]");

  write_file(set / "clip_0001" / "poses.csv", "x,y,yaw\n2,0,0\n2,0,0\n");
  fails_with(eval_args(set, report), "clip clip_0001");
  fails_with(eval_args(set, report), "poses.csv holds 2 pose(s) for the 3 frame(s)");
  write_file(set / "clip_0001" / "poses.csv", "x,y,yaw\n2,0,0\n2,inf,0\n2,0,0\n");
  fails_with(eval_args(set, report), "clip_0001/poses.csv: line 3");
  make_clip(set / "clip_0001", "0,1,0");
  fs::remove(set / "clip_0001" / "frames" / "frame_00.png");
  write_file(set / "clip_0001" / "poses.csv", "x,y,yaw\n2,0,0\n2,0,0\n");
  fails_with(eval_args(set, report), "the model's window needs 3");
  make_clip(set / "clip_0001", "0,1,0");
  write_file(set / "clip_0001" / "future_poses.csv", rows("1,0,0", 14));
  fails_with(eval_args(set, report), "future_poses.csv holds 14 motion(s); 15 are needed");
}

// The one translation unit of this test program that compiles stb.
#include "epona/io/stb_implementation.hpp"

TEST_CASE("eval --solver/--plan-steps/--video-steps: settings, plans per clip, saved frames; Euler by name is the default") {
  TempDir t;
  const fs::path set = make_clip_set(t), plain = t.path / "plain.json", named = t.path / "named.json",
                 mid = t.path / "mid.json", frames = t.path / "frames";
  REQUIRE(cli(eval_args(set, plain)).rc == 0);
  auto args = eval_args(set, named);
  args.insert(args.end(), {"--solver", "euler"});
  REQUIRE(cli(args).rc == 0);
  const json a = read_json(plain), b = read_json(named);
  CHECK(a["model"] == b["model"]);
  CHECK(a["per_clip"] == b["per_clip"]);
  CHECK(a["settings"]["plan_sampler"] == json{{"solver", "euler"}, {"steps", 2}, {"evaluations", 2}});

  args = eval_args(set, mid);
  args.insert(args.end(), {"--solver", "midpoint", "--plan-steps", "3", "--video-steps", "1", "--save-frames", frames.string()});
  const Result r = cli(args);
  INFO(r.err);
  REQUIRE(r.rc == 0);
  const json m = read_json(mid);
  CHECK(m["settings"]["solver"] == "midpoint");
  CHECK(m["settings"]["sampler"] == "official");
  CHECK(m["settings"]["plan_sampler"] == json{{"solver", "midpoint"}, {"steps", 3}, {"evaluations", 6}});
  CHECK(m["settings"]["video_sampler"] == json{{"solver", "midpoint"}, {"steps", 1}, {"evaluations", 2}});
  for (const auto& c : m["per_clip"]) {
    REQUIRE(c["trajectory"].is_array());
    CHECK(c["trajectory"].size() == 15);
    for (int h = 0; h < 2; ++h)
      CHECK(fs::exists(frames / c["name"].get<std::string>() / ("frame_000" + std::to_string(h) + ".png")));
  }
  CHECK(m["per_clip"][0]["trajectory"] != a["per_clip"][0]["trajectory"]);  // another sampler, another plan

  // --sampler fast, its video steps overridden; the note says what runs
  args = eval_args(set, mid);
  args.pop_back();  // -q: keep the notes
  args.insert(args.end(), {"--sampler", "fast", "--video-steps", "1", "--no-plan"});
  const Result f = cli(args);
  INFO(f.err);
  REQUIRE(f.rc == 0);
  CHECK(has(f.err, "video midpoint x 1 step (2 DiT evaluations)"));
  CHECK(read_json(mid)["settings"]["sampler"] == "fast");
}

TEST_CASE("eval --hypotheses 3: the chosen plan, the best of the three, the spread") {
  TempDir t;
  const fs::path set = make_clip_set(t), one = t.path / "one.json", three = t.path / "three.json";
  auto args = eval_args(set, one);
  args.push_back("--no-video");
  REQUIRE(cli(args).rc == 0);
  args = eval_args(set, three);
  for (const char* a : {"--no-video", "--hypotheses", "3"}) args.push_back(a);
  const Result r = cli(args);
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "model_best_of_k"));
  const json j1 = read_json(one), j3 = read_json(three);
  CHECK(j3["settings"]["hypotheses"] == 3);
  CHECK(j3["settings"]["choose"] == "medoid");
  CHECK(j3["hypotheses"]["count"] == 3);
  for (const char* key : {"spread_1s", "spread_2s", "spread_3s"}) check_number(j3["hypotheses"], key);
  for (const char* key : {"l2_1s", "l2_2s", "l2_3s", "l2_avg_3s"}) {
    check_number(j3["model_best_of_k"], key);
    // The best of three includes hypothesis 0, the plan of the one-hypothesis run, and the chosen one.
    CHECK(j3["model_best_of_k"][key].get<double>() <= j1["model"][key].get<double>() + 1e-9);
    CHECK(j3["model_best_of_k"][key].get<double>() <= j3["model"][key].get<double>() + 1e-9);
  }
  CHECK(j3["model_best_of_k"]["collision_rate"].is_null());
  CHECK(j3["per_clip"][0].contains("best_of_k_l2_3s"));
  CHECK(j3["per_clip"][0]["spread_m"].size() == 15);
  CHECK(!j1.contains("model_best_of_k"));
}

namespace {

// Walks two reports side by side: the same keys, the same non-numbers, and numbers within `rel`
// of each other (relative to the larger); the worst relative difference seen goes to `worst`.
void compare_reports(const json& a, const json& b, const std::string& at, double rel, double& worst, int& numbers) {
  INFO(at);
  if (a.is_number() && b.is_number()) {
    const double x = a.get<double>(), y = b.get<double>();
    const double scale = std::max(std::abs(x), std::abs(y));
    const double diff = scale > 0 ? std::abs(x - y) / scale : 0.0;
    worst = std::max(worst, diff);
    ++numbers;
    CHECK(diff <= rel);
    return;
  }
  REQUIRE(a.type() == b.type());
  if (a.is_object()) {
    REQUIRE(a.size() == b.size());
    for (const auto& [key, value] : a.items()) {
      REQUIRE(b.contains(key));
      compare_reports(value, b[key], at + "/" + key, rel, worst, numbers);
    }
  } else if (a.is_array()) {
    REQUIRE(a.size() == b.size());
    for (std::size_t i = 0; i < a.size(); ++i) compare_reports(a[i], b[i], at + "/" + std::to_string(i), rel, worst, numbers);
  } else {
    CHECK(a == b);
  }
}

// Five clips of different last motions (one with boxes), so --batch 4 runs a batch of 4 and one of 1.
fs::path make_five_clips(const TempDir& t) {
  const fs::path set = make_clip_set(t);
  make_clip(set / "clip_0002", "3,0.5,2");
  make_clip(set / "clip_0003", "1,-0.5,-3");
  make_clip(set / "clip_0004", "2.5,0,1");
  return set;
}

}  // namespace

TEST_CASE("eval --batch 4 scores every clip as --batch 1 does: plans, video, control") {
  TempDir t;
  const fs::path set = make_five_clips(t), one = t.path / "one.json", four = t.path / "four.json";
  const std::vector<std::string> extra{"--control", "--control-frames", "1", "--seed", "3", "--threads", "1"};
  auto args = eval_args(set, one);
  args.insert(args.end(), extra.begin(), extra.end());
  REQUIRE(cli(args).rc == 0);
  args = eval_args(set, four);
  args.insert(args.end(), extra.begin(), extra.end());
  args.insert(args.end(), {"--batch", "4"});
  const Result r = cli(args);
  INFO(r.err);
  REQUIRE(r.rc == 0);
  json a = read_json(one), b = read_json(four);
  CHECK(a["settings"]["batch"] == 1);
  CHECK(b["settings"]["batch"] == 4);
  CHECK(a["clips"] == 5);
  b["settings"]["batch"] = 1;  // the one field that differs
  // Not bit for bit: the batched matrix products of the CPU backend block their sums by the row
  // count, so a batch rounds differently from one scene (about 1e-7 of a latent,
  // tests/model/world_item_seeds.cpp); 8-bit frames, PSNR and SSIM carry that on as the odd pixel
  // one level off (measured: worst 1.4e-5 relative, a PSNR; plans within 3e-6).
  double worst = 0;
  int numbers = 0;
  compare_reports(a, b, "", 1e-4, worst, numbers);
  MESSAGE("eval --batch 4 vs --batch 1: ", numbers, " numbers compared, worst relative difference ", worst);
  CHECK(numbers > 100);
}

TEST_CASE("eval --batch: 0 and 65 are refused naming the option and its range") {
  TempDir t;
  const fs::path set = make_clip_set(t), report = t.path / "eval.json";
  for (const char* n : {"0", "65"}) {
    auto args = eval_args(set, report);
    args.insert(args.end(), {"--batch", n});
    const Result r = cli(args);
    CHECK(r.rc == 1);
    CHECK(has(r.err, "--batch must be in [1, 64], got " + std::string(n)));
    CHECK_FALSE(fs::exists(report));
  }
}
