// Tests for epona/io/video_writer.hpp, each video read back with libavformat/libavcodec
// (tests/video_reading.hpp): frame count, size, frame rate, H.264 in yuv420p, colours within
// 4:2:0 rounding of the written ones; odd sizes padded by one pixel; a video written only at its
// end (no temporary file left, nothing at the destination after an error, an unwritable folder or
// no frames); frames of the wrong size refused; the snippet of docs/api.md.
#include <doctest/doctest.h>

#include <array>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

extern "C" {
#include <libavutil/log.h>
}

#include "../temp_dir.hpp"
#include "../video_reading.hpp"
#include "epona/io/image.hpp"
#include "epona/io/video_writer.hpp"

using namespace epona;
namespace fs = std::filesystem;

namespace {

using Rgb = std::array<int, 3>;

// Eight well-separated flat colours, one per frame.
const std::vector<Rgb> kColours = {{200, 30, 30},  {30, 200, 30},  {30, 30, 200},  {220, 220, 40},
                                   {40, 210, 210}, {210, 40, 210}, {240, 240, 240}, {20, 20, 20}};

io::Image flat(std::int64_t h, std::int64_t w, const Rgb& c) {
  io::Image img(h, w);
  for (std::int64_t p = 0; p < h * w; ++p)
    for (int k = 0; k < 3; ++k) img.rgb[static_cast<std::size_t>(p * 3 + k)] = static_cast<std::uint8_t>(c[k]);
  return img;
}

// Mean absolute difference, in levels, between `img` (its top-left h x w) and the flat colour.
double mean_error(const io::Image& img, std::int64_t h, std::int64_t w, const Rgb& c) {
  double sum = 0;
  for (std::int64_t y = 0; y < h; ++y)
    for (std::int64_t x = 0; x < w; ++x)
      for (int k = 0; k < 3; ++k) sum += std::abs(int(img.at(y, x, k)) - c[k]);
  return sum / double(h * w * 3);
}

bool has_temporary(const fs::path& dir) {
  for (const auto& e : fs::directory_iterator(dir))
    if (e.path().filename().string().find(".tmp-") != std::string::npos) return true;
  return false;
}

struct Quiet {  // libx264 reports its statistics at the info level
  Quiet() { av_log_set_level(AV_LOG_ERROR); }
} quiet;

}  // namespace

TEST_CASE("8 flat frames of 64x32 read back: H.264, size, 5 fps, colours within 4:2:0 rounding") {
  test::TempDir t("epona_video");
  std::vector<io::Image> frames;
  for (const auto& c : kColours) frames.push_back(flat(32, 64, c));
  const std::string path = t / "clip.mp4";
  io::write_video(path, frames);
  CHECK_FALSE(has_temporary(t.path));
  const test::DecodedVideo v = test::read_video(path);
  CHECK(v.codec == AV_CODEC_ID_H264);
  CHECK(v.pixel_format == AV_PIX_FMT_YUV420P);
  CHECK(v.height == 32);
  CHECK(v.width == 64);
  CHECK(v.frame_rate.num == 5 * v.frame_rate.den);
  REQUIRE(v.frames.size() == kColours.size());
  for (std::size_t i = 0; i < kColours.size(); ++i) {
    INFO("frame " << i);
    CHECK(mean_error(v.frames[i], 32, 64, kColours[i]) < 8.0);
  }
}

TEST_CASE("the frame rate is the one asked for; frames arrive one by one") {
  test::TempDir t("epona_video");
  io::VideoOptions opt;
  opt.fps = 24;
  io::VideoWriter w(t / "fast.mp4", 32, 64, opt);
  for (int i = 0; i < 3; ++i) w.add(flat(32, 64, kColours[std::size_t(i)]));
  CHECK(w.frames() == 3);
  CHECK_FALSE(fs::exists(t / "fast.mp4"));  // complete only after finish()
  w.finish();
  const test::DecodedVideo v = test::read_video(t / "fast.mp4");
  CHECK(v.frame_rate.num == 24 * v.frame_rate.den);
  CHECK(v.frames.size() == 3);
  CHECK_THROWS_WITH_AS(w.add(flat(32, 64, kColours[0])), doctest::Contains("add() after finish()"), Error);
}

TEST_CASE("odd sizes are padded to even by repeating the last row and column") {
  test::TempDir t("epona_video");
  io::VideoWriter w(t / "odd.mp4", 31, 63);
  CHECK(w.video_height() == 32);
  CHECK(w.video_width() == 64);
  for (int i = 0; i < 2; ++i) w.add(flat(31, 63, kColours[std::size_t(i)]));
  w.finish();
  const test::DecodedVideo v = test::read_video(t / "odd.mp4");
  CHECK(v.height == 32);
  CHECK(v.width == 64);
  REQUIRE(v.frames.size() == 2);
  for (std::size_t i = 0; i < 2; ++i) CHECK(mean_error(v.frames[i], 32, 64, kColours[i]) < 8.0);  // padding too
}

TEST_CASE("nothing is written without frames, into a missing folder, or at bad sizes and rates") {
  test::TempDir t("epona_video");
  CHECK_THROWS_WITH_AS(io::write_video(t / "none.mp4", {}), doctest::Contains("at least one frame"), Error);
  {
    io::VideoWriter w(t / "empty.mp4", 32, 64);
    CHECK_THROWS_WITH_AS(w.finish(), doctest::Contains("at least one frame; none was given"), Error);
  }
  CHECK_THROWS_WITH_AS(io::write_video(t / "no/such/dir/x.mp4", {flat(32, 64, kColours[0])}),
                       doctest::Contains("cannot create the temporary file"), Error);
  fs::create_directories(t.path / "folder.mp4");
  CHECK_THROWS_WITH_AS(io::write_video(t / "folder.mp4", {flat(32, 64, kColours[0])}),
                       doctest::Contains("is a directory"), Error);
  io::VideoOptions opt;
  opt.fps = 0;
  CHECK_THROWS_WITH_AS(io::write_video(t / "zero.mp4", {flat(32, 64, kColours[0])}, opt),
                       doctest::Contains("frame rate 0 fps is outside 1..120"), Error);
  opt = {};
  opt.crf = 52;
  CHECK_THROWS_WITH_AS(io::VideoWriter(t / "crf.mp4", 32, 64, opt), doctest::Contains("crf 52 is outside"), Error);
  {
    io::VideoWriter w(t / "mixed.mp4", 32, 64);
    w.add(flat(32, 64, kColours[0]));
    CHECK_THROWS_WITH_AS(w.add(flat(64, 32, kColours[1])),
                         doctest::Contains("frame 1 is 64x32, the video's frames are 32x64"), Error);
  }  // dropped before finish(): the partial file goes with it
  CHECK_FALSE(fs::exists(t / "none.mp4"));
  CHECK_FALSE(fs::exists(t / "empty.mp4"));
  CHECK_FALSE(fs::exists(t / "zero.mp4"));
  CHECK_FALSE(fs::exists(t / "crf.mp4"));
  CHECK_FALSE(fs::exists(t / "mixed.mp4"));
  CHECK_FALSE(has_temporary(t.path));
}

TEST_CASE("the temporary file is listed for the signal handler while the video is written") {
  test::TempDir t("epona_video");
  io::VideoWriter w(t / "listed.mp4", 32, 64);
  w.add(flat(32, 64, kColours[0]));
  REQUIRE(has_temporary(t.path));
  io::remove_temporary_files();  // what the program's SIGINT handler does
  CHECK_FALSE(has_temporary(t.path));
}

// The snippet of docs/api.md ("Video"), on decoder-shaped output: (N, 3, H, W) in [-1, 1].
TEST_CASE("the docs/api.md snippet writes the decoded frames") {
  test::TempDir t("epona_video");
  const fs::path previous = fs::current_path();
  fs::current_path(t.path);
  const Tensor<float> images = Tensor<float>::zeros({3, 3, 32, 64});
  io::VideoWriter video("clip.mp4", images.size(2), images.size(3), {.fps = 5});
  for (std::int64_t i = 0; i < images.size(0); ++i) video.add(io::tensor_to_image(images, i));
  video.finish();  // clip.mp4 appears only now, complete
  fs::current_path(previous);
  CHECK(test::read_video(t / "clip.mp4").frames.size() == 3);
}

#include "epona/io/stb_implementation.hpp"
