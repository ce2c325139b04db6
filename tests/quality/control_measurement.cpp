// Is `eval --control`'s instrument sound? `eval::horizontal_shift` (eval/control_metrics.hpp) is
// applied to frames whose turn is known: on 50 held-out scenes (`epona synth --seed 4242`, clips
// 0..49 at its defaults of 10 history frames + 15 future motions), the synthetic camera renders
// the last history frame's world from the pose `eval --control` asks the model for — one frame on,
// at least 2 m ahead, turned +5° and −5°. A sound instrument reads the left view's content right
// of the right view's (shift > 0) and about the pinhole camera's focal·tan(10°) ≈ 59 px.
// This checks the instrument, not the model: the bundled model's own agree rate (0.10 on these
// scenes, it ignores the yaw action) is what `eval --control` reports and docs/evaluation.md
// documents; it is not asserted here.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <vector>

#include "epona/eval/control_metrics.hpp"
#include "epona/synth/scenario.hpp"

using namespace epona;

namespace {

constexpr std::uint64_t kSeed = 4242;      // the held-out scenes
constexpr std::int64_t kScenes = 50;
constexpr std::int64_t kHistory = 10;      // the bundled model's condition frames
constexpr std::int64_t kRecorded = 10 + 15;  // `epona synth`'s defaults: frames + future motions
constexpr double kYawDeg = 5;              // `eval --control`'s default
constexpr double kMinForward = 2;          // as `eval --control` (kControlMinForward)

}  // namespace

TEST_CASE("control measurement: rendered turns of the held-out scenes read the right way and size") {
  synth::RenderOptions ro;  // 256x512, the model's frames
  ro.supersample = 1;       // the shift is a whole-column search: antialiasing does not change it
  const double focal = ro.camera.focal();
  const double expected = focal * std::tan(synth::rad(2 * kYawDeg));  // about 59 px

  std::vector<double> shifts;
  std::ostringstream log;
  int agree = 0;
  for (std::int64_t k = 0; k < kScenes; ++k) {
    const synth::Scenario sc(kSeed, static_cast<std::uint64_t>(k), kRecorded);
    const std::int64_t last = kHistory - 1;
    const synth::Pose2 e = sc.frames()[static_cast<std::size_t>(last)].ego;
    const double forward = std::max(sc.motion(last).x, kMinForward);
    synth::Pose2 left{e.x + forward * std::cos(e.yaw), e.y + forward * std::sin(e.yaw), e.yaw}, right = left;
    left.yaw += synth::rad(kYawDeg);
    right.yaw -= synth::rad(kYawDeg);
    const eval::ShiftEstimate s = eval::horizontal_shift(sc.render(last, ro, left), sc.render(last, ro, right));
    shifts.push_back(double(s.shift));
    agree += s.shift > 0;
    log << k << ":" << s.shift << " ";
  }
  std::vector<double> sorted = shifts;
  std::sort(sorted.begin(), sorted.end());
  const double median = 0.5 * (sorted[kScenes / 2 - 1] + sorted[kScenes / 2]);
  MESSAGE("shifts (px) ", log.str(), "| agree ", agree, "/", kScenes, ", median ", median, " px, min ",
          sorted.front(), ", max ", sorted.back(), ", pinhole ", expected, " px");
  CHECK(agree >= kScenes - 1);
  CHECK(std::abs(median - expected) <= 0.25 * expected);
}
