// Tests of the trajectory-control shift estimator (include/epona/eval/control_metrics.hpp): images
// shifted by a known number of columns, both ways, read back with that shift and its sign (a's
// content right of b's is positive); noise and a brightness change do not move it; identical or
// featureless images read 0; only the compared rows count; bad sizes and searches are refused.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <string>

#include "epona/core/error.hpp"
#include "epona/eval/control_metrics.hpp"
#include "epona/io/image.hpp"

using namespace epona;
using namespace epona::eval;

namespace {

// A road-like scene: sky above, a grey road with white dashed markings converging on a vanishing
// point and random texture below, wide enough that a shifted crop of it stays inside.
io::Image scene(std::int64_t h, std::int64_t w, std::uint32_t seed) {
  std::mt19937 gen(seed);
  std::uniform_int_distribution<int> grain(-12, 12);
  io::Image img(h, w);
  const double vx = 0.55 * double(w), vy = 0.4 * double(h);
  for (std::int64_t y = 0; y < h; ++y)
    for (std::int64_t x = 0; x < w; ++x) {
      int v = 0;
      if (double(y) < vy) {
        v = 180 + int(20 * std::sin(0.05 * double(x)));
      } else {
        const double depth = (double(y) - vy) / (double(h) - vy);  // 0 at the horizon, 1 at the bottom
        v = 90 + grain(gen);
        for (const double lane : {-1.5, -0.5, 0.5, 1.5}) {
          const double centre = vx + lane * depth * 0.5 * double(w);
          const bool dash = lane == -0.5 || lane == 0.5 ? std::fmod(1.0 / (depth + 0.05), 1.0) < 0.5 : true;
          if (dash && std::abs(double(x) - centre) < 1 + 4 * depth) v = 235;
        }
        if (std::abs(double(x) - vx + 0.9 * depth * double(w)) < 30 * depth) v = 60 + grain(gen);  // a verge
      }
      for (int c = 0; c < 3; ++c) img.at(y, x, c) = static_cast<std::uint8_t>(std::clamp(v + 5 * c, 0, 255));
    }
  return img;
}

// Columns [left, left + w) of `src`.
io::Image crop(const io::Image& src, std::int64_t left, std::int64_t w) {
  io::Image out(src.height, w);
  for (std::int64_t y = 0; y < src.height; ++y)
    for (std::int64_t x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) out.at(y, x, c) = src.at(y, left + x, c);
  return out;
}

io::Image with_noise(io::Image img, std::uint32_t seed, int amplitude, int offset = 0) {
  std::mt19937 gen(seed);
  std::uniform_int_distribution<int> d(-amplitude, amplitude);
  for (auto& v : img.rgb) v = static_cast<std::uint8_t>(std::clamp(int(v) + offset + d(gen), 0, 255));
  return img;
}

}  // namespace

TEST_CASE("horizontal_shift: a known shift, both signs, several sizes") {
  const io::Image world = scene(128, 512, 1);
  const std::int64_t W = 256, origin = 128;
  const io::Image b = crop(world, origin, W);
  for (const std::int64_t s : {-60, -25, -7, -1, 1, 3, 18, 47, 63}) {
    INFO("shift " << s);
    // a(x) = world(origin - s + x) = b(x - s): a's content lies s columns right of b's.
    const io::Image a = crop(world, origin - s, W);
    const ShiftEstimate e = horizontal_shift(a, b);
    CHECK(e.shift == s);
    CHECK(e.mad < 1e-9);
    CHECK(e.mad_at_zero > 1.0);
    CHECK(horizontal_shift(b, a).shift == -s);  // swapping the frames flips the sign
  }
}

TEST_CASE("horizontal_shift: noise and a brightness change between the frames do not move it") {
  const io::Image world = scene(96, 640, 2);
  const io::Image b = crop(world, 160, 320);
  for (const std::int64_t s : {-40, 12, 35}) {
    INFO("shift " << s);
    const io::Image a = with_noise(crop(world, 160 - s, 320), 7 + static_cast<std::uint32_t>(s + 100), 20, 8);
    CHECK(horizontal_shift(a, with_noise(b, 3, 20)).shift == s);
  }
}

TEST_CASE("horizontal_shift: no shift, no texture, and the rows compared") {
  const io::Image b = crop(scene(128, 512, 3), 128, 256);
  CHECK(horizontal_shift(b, b).shift == 0);
  io::Image flat(64, 128);
  for (auto& v : flat.rgb) v = 100;
  const ShiftEstimate e = horizontal_shift(flat, flat);
  CHECK(e.shift == 0);  // every candidate ties: the smallest |shift| wins, no turn read
  CHECK(e.mad == 0);

  // Only the rows searched count: the lower half moves right by 9, the upper half left by 20.
  const io::Image world = scene(128, 512, 4);
  io::Image a = crop(world, 128 - 9, 256);
  const io::Image up = crop(world, 128 + 20, 256);
  for (std::int64_t y = 0; y < 64; ++y)
    for (std::int64_t x = 0; x < 256; ++x)
      for (int c = 0; c < 3; ++c) a.at(y, x, c) = up.at(y, x, c);
  CHECK(horizontal_shift(a, b).shift == 9);  // default: the lower half
  CHECK(horizontal_shift(a, b, {0, 64, -1}).shift == -20);
  CHECK(horizontal_shift(a, b, {64, 128, 8}).shift == 8);  // the search range clips the answer
}

TEST_CASE("horizontal_shift: bad inputs") {
  const io::Image a(32, 64), b(32, 96);
  CHECK_THROWS_AS(horizontal_shift(a, b), Error);
  CHECK_THROWS_AS(horizontal_shift(a, a, {20, 10, -1}), Error);
  CHECK_THROWS_AS(horizontal_shift(a, a, {0, 33, -1}), Error);
  CHECK_THROWS_AS(horizontal_shift(a, a, {-1, -1, 32}), Error);
  CHECK_THROWS_AS(horizontal_shift(io::Image(), io::Image()), Error);
}
