// Tests of the evaluation library (include/epona/eval/): PSNR and SSIM against plain float64
// references written independently (direct 2-D window sums) and analytic values, SE(2)
// composition, L2 at/up to 1/2/3 s, the separating-axis collision test, the baselines, and the
// clip-set reader's checks and error messages.
#include <doctest/doctest.h>

#include <algorithm>
#include <functional>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "epona/eval/baselines.hpp"
#include "epona/eval/clip_set.hpp"
#include "epona/eval/ground_truth.hpp"
#include "epona/eval/image_metrics.hpp"
#include "epona/eval/planning_metrics.hpp"
#include "epona/io/image.hpp"
#include "../temp_dir.hpp"
#include "../files.hpp"
#include "../error_text.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::contains;
using epona::test::write_file;
using epona::test::TempDir;
using namespace epona::eval;

namespace {

io::Image random_image(std::int64_t h, std::int64_t w, std::uint32_t seed, int lo = 0, int hi = 255) {
  std::mt19937 gen(seed);
  std::uniform_int_distribution<int> d(lo, hi);
  io::Image img(h, w);
  for (auto& v : img.rgb) v = static_cast<std::uint8_t>(d(gen));
  return img;
}

// SSIM by its definition: for every position where the 11x11 window fits, the Gaussian-weighted
// statistics summed directly over the 2-D window; the map averaged, then the channels.
double reference_ssim(const io::Image& a, const io::Image& b) {
  const int r = 5;
  const double sigma = 1.5, c1 = std::pow(0.01 * 255, 2), c2 = std::pow(0.03 * 255, 2);
  double wsum = 0;
  std::vector<double> w((2 * r + 1) * (2 * r + 1));
  for (int i = -r; i <= r; ++i)
    for (int j = -r; j <= r; ++j) wsum += w[(i + r) * (2 * r + 1) + j + r] = std::exp(-(i * i + j * j) / (2 * sigma * sigma));
  double total = 0;
  for (int c = 0; c < 3; ++c) {
    double sum = 0;
    std::int64_t count = 0;
    for (std::int64_t y = r; y < a.height - r; ++y)
      for (std::int64_t x = r; x < a.width - r; ++x) {
        double mx = 0, my = 0, sxx = 0, syy = 0, sxy = 0;
        for (int i = -r; i <= r; ++i)
          for (int j = -r; j <= r; ++j) {
            const double k = w[(i + r) * (2 * r + 1) + j + r] / wsum;
            const double p = a.at(y + i, x + j, c), q = b.at(y + i, x + j, c);
            mx += k * p, my += k * q, sxx += k * p * p, syy += k * q * q, sxy += k * p * q;
          }
        const double vx = sxx - mx * mx, vy = syy - my * my, cov = sxy - mx * my;
        sum += (2 * mx * my + c1) * (2 * cov + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2));
        ++count;
      }
    total += sum / double(count);
  }
  return total / 3;
}

std::string error_of(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("PSNR: identical images give the documented cap; a constant shift gives 10 log10(255^2 / d^2)") {
  const io::Image a = random_image(16, 20, 1, 10, 200);
  CHECK(psnr(a, a) == kPsnrCap);
  io::Image b = a;
  for (auto& v : b.rgb) v = static_cast<std::uint8_t>(v + 7);
  CHECK(psnr(a, b) == doctest::Approx(10 * std::log10(255.0 * 255.0 / 49.0)).epsilon(1e-12));
  CHECK(psnr(b, a) == psnr(a, b));
  const io::Image c = random_image(16, 20, 2);
  double sse = 0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) sse += std::pow(double(a.rgb[i]) - double(c.rgb[i]), 2);
  CHECK(psnr(a, c) == doctest::Approx(20 * std::log10(255.0) - 10 * std::log10(sse / double(a.rgb.size()))).epsilon(1e-12));
  CHECK(contains(error_of([&] { psnr(a, random_image(16, 21, 3)); }), "differ in size"));
}

TEST_CASE("SSIM: 1 for identical images, the luminance term for constant images, equal to a direct 2-D reference") {
  const io::Image a = random_image(24, 30, 4);
  CHECK(ssim(a, a) == doctest::Approx(1.0).epsilon(1e-12));
  io::Image flat(16, 16), shifted(16, 16);
  for (auto& v : flat.rgb) v = 100;
  for (auto& v : shifted.rgb) v = 140;
  const double c1 = std::pow(0.01 * 255, 2);
  CHECK(ssim(flat, shifted) == doctest::Approx((2 * 100.0 * 140 + c1) / (100.0 * 100 + 140.0 * 140 + c1)).epsilon(1e-12));
  const io::Image b = random_image(24, 30, 5);
  CHECK(ssim(a, b) == doctest::Approx(reference_ssim(a, b)).epsilon(1e-10));
  io::Image noisy = a;  // a correlated pair: SSIM well inside (0, 1)
  std::mt19937 gen(6);
  for (auto& v : noisy.rgb) v = static_cast<std::uint8_t>(std::clamp<int>(v + int(gen() % 41) - 20, 0, 255));
  const double s = ssim(a, noisy);
  CHECK(s == doctest::Approx(reference_ssim(a, noisy)).epsilon(1e-10));
  CHECK(s > 0.5);
  CHECK(s < 1.0);
  CHECK(contains(error_of([&] { ssim(random_image(10, 40, 1), random_image(10, 40, 2)); }), "smaller than the 11x11"));
}

TEST_CASE("SE(2): composition and cumulative poses") {
  const Pose2 p = compose({1, 0, 90}, {1, 0, 0});
  CHECK(p.x == doctest::Approx(1));
  CHECK(p.y == doctest::Approx(1));
  CHECK(p.yaw == doctest::Approx(90));
  const Pose2 q = compose({2, 3, 30}, compose({-1, 0.5, -45}, {0.25, 4, 10}));  // associativity
  const Pose2 r = compose(compose({2, 3, 30}, {-1, 0.5, -45}), {0.25, 4, 10});
  CHECK(q.x == doctest::Approx(r.x));
  CHECK(q.y == doctest::Approx(r.y));
  CHECK(q.yaw == doctest::Approx(r.yaw));
  io::PoseSequence m;
  for (int i = 0; i < 4; ++i) m.x.push_back(2), m.y.push_back(0), m.yaw.push_back(90);
  const auto c = cumulative_poses(m, 4);  // a square: 2 m forward, turn left, four times
  CHECK(c[0].x == doctest::Approx(2));
  CHECK(c[1].x == doctest::Approx(2));
  CHECK(c[1].y == doctest::Approx(2));
  CHECK(c[2].x == doctest::Approx(0));
  CHECK(c[2].y == doctest::Approx(2));
  CHECK(c[3].x == doctest::Approx(0).epsilon(1e-12));
  CHECK(std::abs(c[3].y) < 1e-12);
  CHECK(c[3].yaw == doctest::Approx(360));
  CHECK_THROWS(cumulative_poses(m, 5));
}

TEST_CASE("L2 at and up to 1/2/3 s") {
  std::vector<Pose2> truth(15), plan(15);
  for (std::size_t n = 0; n < 15; ++n) truth[n] = {double(n + 1), 0, 0}, plan[n] = {double(n + 1) + 3, 4, 0};
  L2Errors e = l2_errors(plan, truth);
  for (int k = 0; k < 3; ++k) {
    CHECK(e.at[k] == doctest::Approx(5));
    CHECK(e.avg[k] == doctest::Approx(5));
  }
  for (std::size_t n = 0; n < 15; ++n) truth[n] = {}, plan[n] = {0, double(n + 1), 0};
  e = l2_errors(plan, truth);
  CHECK(e.at[0] == doctest::Approx(5));
  CHECK(e.at[1] == doctest::Approx(10));
  CHECK(e.at[2] == doctest::Approx(15));
  CHECK(e.avg[0] == doctest::Approx(3));    // mean of 1..5
  CHECK(e.avg[1] == doctest::Approx(5.5));  // mean of 1..10
  CHECK(e.avg[2] == doctest::Approx(8));    // mean of 1..15
  CHECK_THROWS(l2_errors(std::vector<Pose2>(14), truth));
}

TEST_CASE("separating-axis collision: overlap, touching, separated, rotated near-miss") {
  const Box2 a{0, 0, 0, 4, 2};
  CHECK(boxes_overlap(a, {0, 0, 0, 4, 2}));
  CHECK(boxes_overlap(a, {1, 0.5, 30, 1, 1}));
  CHECK(boxes_overlap(a, {0, 0, 0, 0.5, 0.5}));       // inside
  CHECK(boxes_overlap(a, {4, 0, 0, 4, 2}));           // edges touching: a collision
  CHECK_FALSE(boxes_overlap(a, {4 + 1e-9, 0, 0, 4, 2}));
  CHECK_FALSE(boxes_overlap(a, {0, 2.5, 0, 4, 2}));
  // A 2x2 square turned 45 degrees beyond a's corner (2, 1): the boxes' bounding boxes overlap,
  // the boxes do not (separated along the square's edge normal (1, 1)/sqrt 2 once d > sqrt(2)/2).
  CHECK_FALSE(boxes_overlap(a, {2.75, 1.75, 45, 2, 2}));
  CHECK_FALSE(boxes_overlap({2.75, 1.75, 45, 2, 2}, a));
  CHECK(boxes_overlap(a, {2.65, 1.65, 45, 2, 2}));
  CHECK(boxes_overlap({0, 0, 90, 4, 2}, {0, 1.9, 0, 1, 1}));  // a's heading turns its long side along y
  CHECK_FALSE(boxes_overlap({0, 0, 0, 4, 2}, {0, 1.9, 0, 1, 1.6}));
}

TEST_CASE("plan collisions per horizon, and none where the boxes stop") {
  std::vector<Pose2> plan(15);
  for (std::size_t n = 0; n < 15; ++n) plan[n] = {2.0 * double(n + 1), 0, 0};
  FutureBoxes boxes(15);
  boxes[7].push_back({16, 0, 0, 4, 2});  // where waypoint 7 is, at its frame only
  Collisions c = plan_collisions(plan, {4, 2}, boxes);
  CHECK(c[0] == false);
  CHECK(c[1] == true);
  CHECK(c[2] == true);
  boxes[7].clear();
  boxes[8].push_back({16, 0, 0, 4, 2});  // the same place a frame later: the ego has moved on by 2 m (touching: hit)
  CHECK(plan_collisions(plan, {4, 2}, boxes)[1] == true);
  boxes[8] = {{16, 5, 0, 4, 2}};
  CHECK(plan_collisions(plan, {4, 2}, boxes)[2] == false);
  c = plan_collisions(plan, {4, 2}, FutureBoxes(7));
  CHECK(c[0] == false);
  CHECK_FALSE(c[1].has_value());
  CHECK_FALSE(c[2].has_value());
}

TEST_CASE("baselines: constant velocity, constant turn, repeat last") {
  const auto cv = constant_velocity({2, 0.5, 10}, 3);
  CHECK(cv[2].x == doctest::Approx(6));
  CHECK(cv[2].y == doctest::Approx(1.5));
  CHECK(cv[2].yaw == 0);
  const auto ct = constant_turn({1, 0, 90}, 4);
  CHECK(ct[1].x == doctest::Approx(1));
  CHECK(ct[1].y == doctest::Approx(1));
  CHECK(ct[2].x == doctest::Approx(0).epsilon(1e-12));
  CHECK(ct[2].y == doctest::Approx(1));
  CHECK(ct[3].yaw == doctest::Approx(360));
  const auto straight = constant_turn({2, 0.5, 0}, 15), cv15 = constant_velocity({2, 0.5, 0}, 15);
  for (std::size_t n = 0; n < 15; ++n) CHECK(distance(straight[n], cv15[n]) < 1e-12);
  const std::vector<io::Image> h{random_image(4, 4, 1), random_image(4, 4, 2)};
  CHECK(repeat_last_frame(h).rgb == h[1].rgb);
}

TEST_CASE("clip sets: natural order, optional parts, errors naming the clip and the file") {
  TempDir t;
  const io::Image img = random_image(16, 16, 1);
  const auto make_clip = [&](const std::string& name, int frames) {
    fs::create_directories(t.path / name / "frames");
    for (int i = 0; i < frames; ++i) io::write_png((t.path / name / "frames" / ("frame_0" + std::to_string(i) + ".png")).string(), img);
    std::string poses = "x,y,yaw\n";
    for (int i = 0; i < frames; ++i) poses += "1,0,0\n";
    write_file(t.path / name / "poses.csv", poses);
  };
  CHECK(contains(error_of([&] { find_clip_folders(t.path / "missing"); }), "no such folder"));
  CHECK(contains(error_of([&] { find_clip_folders(t.path); }), "no clips"));
  make_clip("clip_10", 3);
  make_clip("clip_2", 3);
  fs::create_directories(t.path / "not_a_clip");
  const auto folders = find_clip_folders(t.path);
  REQUIRE(folders.size() == 2);
  CHECK(folders[0].filename() == "clip_2");
  const auto single = find_clip_folders(t.path / "clip_10");  // a clip folder alone is a set of one
  REQUIRE(single.size() == 1);
  CHECK(single[0] == t.path / "clip_10");
  const EvalClip c = read_clip(folders[0]);
  CHECK(c.frames.size() == 3);
  CHECK_FALSE(c.future_motions.has_value());
  CHECK_FALSE(c.boxes.has_value());
  CHECK_NOTHROW(check_clip(c, {3, 15, 5}));  // no future parts: nothing to check
  CHECK(contains(error_of([&] { check_clip(c, {4, 15, 5}); }), "clip clip_2"));

  write_file(t.path / "clip_2" / "poses.csv", "x,y,yaw\n1,0,0\n");
  std::string e = error_of([&] { read_clip(folders[0]); });
  CHECK(contains(e, "clip clip_2"));
  CHECK(contains(e, "poses.csv holds 1 pose(s) for the 3 frame(s)"));
  write_file(t.path / "clip_2" / "poses.csv", "x,y,yaw\n1,0,0\n1,nan,0\n1,0,0\n");
  CHECK(contains(error_of([&] { read_clip(folders[0]); }), "poses.csv: line 3"));

  make_clip("clip_2", 3);
  write_file(t.path / "clip_2" / "future_poses.csv", "x,y,yaw\n1,0,0\n");
  e = error_of([&] { check_clip(read_clip(folders[0]), {3, 15, 0}); });
  CHECK(contains(e, "future_poses.csv holds 1 motion(s); 15 are needed"));
  fs::create_directories(t.path / "clip_2" / "future");
  io::write_png((t.path / "clip_2" / "future" / "frame_00.png").string(), img);
  std::string future = "x,y,yaw\n";
  for (int i = 0; i < 15; ++i) future += "1,0,0\n";
  write_file(t.path / "clip_2" / "future_poses.csv", future);
  CHECK(contains(error_of([&] { check_clip(read_clip(folders[0]), {3, 15, 2}); }), "--horizon asks for 2"));
  CHECK_NOTHROW(check_clip(read_clip(folders[0]), {3, 15, 1}));

  write_file(t.path / "clip_2" / "boxes.json", R"({"ego": {"length": 4, "width": 2}, "frames": [[], [], [], [{"x": 5, "y": 0, "yaw": 0, "length": 4, "width": 2}]]})");
  const EvalClip b = read_clip(folders[0]);
  REQUIRE(b.boxes.has_value());
  CHECK(b.boxes->ego.length == 4);
  REQUIRE(b.future_boxes().size() == 1);
  CHECK(b.future_boxes()[0][0].x == 5);
  write_file(t.path / "clip_2" / "boxes.json", R"({"ego": {"length": 4, "width": 2}, "frames": [[], []]})");
  CHECK(contains(error_of([&] { read_clip(folders[0]); }), "boxes.json holds 2 frame(s) of boxes"));
  write_file(t.path / "clip_2" / "boxes.json", R"({"ego": {"length": 4, "width": 2}, "frames": [[], [], [{"x": 1, "y": 0, "yaw": 0, "length": -1, "width": 2}]]})");
  e = error_of([&] { read_clip(folders[0]); });
  CHECK(contains(e, "boxes.json: frame 2, box 0"));
  CHECK(contains(e, "\"length\" must be positive"));
  write_file(t.path / "clip_2" / "boxes.json", "{");
  CHECK(contains(error_of([&] { read_clip(folders[0]); }), "boxes.json: invalid JSON"));
}

// The one translation unit of this test program that compiles stb (write_png above).
#include "epona/io/stb_implementation.hpp"
