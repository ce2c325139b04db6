// Tests of the `epona` program's --video (apps/epona/video_output.hpp), run in-process: generate
// on the bundled model writes an MP4 of the input frames then the generated ones, read back with
// libavformat/libavcodec (tests/video_reading.hpp); decode --video; the options refused before any
// work (--fps out of range or without --video, a name that is not .mp4, a folder). Built only
// when the build has FFmpeg's libraries.
#include <doctest/doctest.h>

#include <cmath>
#include <filesystem>
#include <string>
#include <vector>

#include "../temp_dir.hpp"
#include "../video_reading.hpp"
#include "cli_testing.hpp"
#include "epona/io/image.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/image_folder.hpp"
#include "epona/io/npy.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::check_cli_error;

namespace {

using test::cli;
using test::has;

const io::ModelConfigs& demo_configs() {
  static const io::ModelConfigs c = io::load_configs(std::string(EPONA_TEST_DATA_DIR) + "/golden/configs.json");
  return c;
}

// Mean absolute difference of two images of one size, in levels.
double mean_error(const io::Image& a, const io::Image& b) {
  REQUIRE(a.rgb.size() == b.rgb.size());
  double sum = 0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) sum += std::abs(int(a.rgb[i]) - int(b.rgb[i]));
  return sum / double(a.rgb.size());
}

}  // namespace

TEST_CASE("generate --video: the input frames then the generated ones, H.264 at --fps") {
  test::TempDir t("epona_cli_video");
  const auto& w = demo_configs().world;
  const test::CliResult r =
      cli({"generate", "-n", "2", "--steps", "1", "--latents", "--out", t / "g", "--video", t / "g/clip.mp4", "-q"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "wrote " + (t / "g/clip.mp4") + " (" + std::to_string(w.condition_frames + 2) + " frame(s) of "));
  const test::DecodedVideo v = test::read_video(t / "g/clip.mp4");
  CHECK(v.codec == AV_CODEC_ID_H264);
  CHECK(v.height == w.image_h);
  CHECK(v.width == w.image_w);
  CHECK(v.frame_rate.num == 5 * v.frame_rate.den);  // Epona's 5 Hz by default
  REQUIRE(static_cast<std::int64_t>(v.frames.size()) == w.condition_frames + 2);
  // The inputs come first, within H.264's loss of smooth pictures; the generated frames follow in
  // order (the golden model's random weights make them noise, which 4:2:0 cannot keep: each is only
  // checked to be nearer its own PNG than the other one).
  const auto inputs = io::image_files(std::string(EPONA_TEST_DATA_DIR) + "/demo", "test");
  for (std::size_t i = 0; i < inputs.size(); ++i) {
    INFO("input frame " << i);
    CHECK(mean_error(v.frames[i], io::read_image(inputs[i].string())) < 8.0);
  }
  const io::Image g0 = io::read_image(t / "g/frames/frame_0000.png"), g1 = io::read_image(t / "g/frames/frame_0001.png");
  const std::size_t F = inputs.size();
  CHECK(mean_error(v.frames[F], g0) < mean_error(v.frames[F], g1));
  CHECK(mean_error(v.frames[F + 1], g1) < mean_error(v.frames[F + 1], g0));

  // decode --video on the latents it wrote, at another rate.
  const test::CliResult d = cli({"decode", t / "g/latents.npy", "-o", t / "d", "--video", t / "d.mp4", "--fps", "12", "-q"});
  INFO(d.err);
  REQUIRE(d.rc == 0);
  CHECK(has(d.out, "wrote " + (t / "d.mp4") + " (2 frame(s) of "));
  const test::DecodedVideo dv = test::read_video(t / "d.mp4");
  CHECK(dv.frames.size() == 2);
  CHECK(dv.frame_rate.num == 12 * dv.frame_rate.den);
}

TEST_CASE("--video and --fps are refused before any work, naming the problem") {
  test::TempDir t("epona_cli_video");
  check_cli_error(cli({"generate", "--video", t / "x.mp4", "--fps", "0", "--out", t / "g"}), "--fps must be in [1, 120], got 0");
  check_cli_error(cli({"generate", "--video", t / "x.mp4", "--fps", "121", "--out", t / "g"}),
              "--fps must be in [1, 120], got 121");
  check_cli_error(cli({"generate", "--fps", "10", "--out", t / "g"}), "--fps sets the frame rate of --video");
  check_cli_error(cli({"generate", "--video", t / "x.avi", "--out", t / "g"}),
              "x.avi: epona writes H.264 in MP4 only; give a file name ending in .mp4");
  fs::create_directories(t.path / "folder.mp4");
  check_cli_error(cli({"generate", "--video", t / "folder.mp4", "--out", t / "g"}), "is a folder, not a file name");
  const fs::path file = t.path / "file";
  io::write_atomically(file, "not a folder");
  check_cli_error(cli({"generate", "--video", (file / "x.mp4").string(), "--out", t / "g"}), "is a file, not a folder");
  CHECK_FALSE(fs::exists(t.path / "g"));  // refused before the output folder was made
  io::write_npy(t / "z.npy", Tensor<float>::zeros({1, demo_configs().dcae.latent_channels, 1, 2}));
  check_cli_error(cli({"decode", t / "z.npy", "-o", t / "d", "--video", t / "z.webm"}), "--decode clip");
}

#include "epona/io/stb_implementation.hpp"
