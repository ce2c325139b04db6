// Issue #36, resource policy (io/limits.hpp) at the readers: images with a side beyond the limit
// are refused before decoding; resizing keeps its intermediate image within the pixel limit (a
// tall strip widened went through a 16.7M x 1024 intermediate); CSV rows split a bounded number of
// fields; the JSON value limit holds.
#include <doctest/doctest.h>

#include <cstdint>
#include <string>
#include <vector>

#include <fstream>
#include <iterator>

#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "epona/io/image.hpp"  // stb_image_write.h too
#include "epona/io/limits.hpp"

using namespace epona;

namespace {

std::vector<std::uint8_t> png_of(int w, int h) {
  std::vector<std::uint8_t> pixels(std::size_t(w) * std::size_t(h) * 3, 128), out;
  stbi_write_png_to_func(
      [](void* ctx, void* data, int n) {
        auto* v = static_cast<std::vector<std::uint8_t>*>(ctx);
        v->insert(v->end(), static_cast<std::uint8_t*>(data), static_cast<std::uint8_t*>(data) + n);
      },
      &out, w, h, 3, pixels.data(), w * 3);
  return out;
}

}  // namespace

TEST_CASE("image: a side beyond max_side is refused before decoding") {
  const auto strip = png_of(io::limits::kImageSide + 1, 1);
  io::ImageReadOptions opt;
  opt.convert_to_rgb8 = true;
  CHECK_THROWS_WITH_AS(io::decode_image(strip, "strip.png", opt),
                       doctest::Contains("a side longer than the limit of 16384"), Error);
  opt.max_side = io::limits::kImageSide + 1;
  opt.size = io::SizePolicy::Resize, opt.height = 32, opt.width = 64;
  const io::Image img = io::decode_image(strip, "strip.png", opt);
  CHECK(img.height == 32);
  CHECK(img.width == 64);
}

TEST_CASE("resize: the pass order keeps the intermediate within the pixel limit") {
  io::Image tall(4096, 1);
  std::fill(tall.rgb.begin(), tall.rgb.end(), 200);
  // PIL's order (horizontal first) would build 4096 x 64; the limit of 8192 pixels allows only
  // the vertical pass first (32 x 1), then 32 x 64.
  const io::Image out = io::resize_bicubic(tall, 32, 64, 8192);
  CHECK(out.height == 32);
  CHECK(out.width == 64);
  for (auto v : out.rgb) CHECK(v == 200);
  // PIL's order is kept whenever it fits: the result equals the unlimited resize.
  io::Image img(64, 48);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) img.rgb[i] = static_cast<std::uint8_t>(i * 37 % 251);
  CHECK(io::resize_bicubic(img, 32, 96, 32 * 96 + 64 * 96).rgb == io::resize_bicubic(img, 32, 96).rgb);
  // Neither order fits, or the target itself is too large: a named error, nothing allocated.
  CHECK_THROWS_WITH_AS(io::resize_bicubic(tall, 32, 64, 1000), doctest::Contains("more than the limit of 1000"), Error);
  CHECK_THROWS_WITH_AS(io::resize_bicubic(img, 65536, 65536), doctest::Contains("more than the limit of 33554432 pixels"),
                       Error);
}

TEST_CASE("CSV: a line of millions of separators is one short error") {
  const std::string line(10'000'000, ',');
  const auto fields = io::poses_detail::split_fields(line);
  CHECK(fields.size() == io::limits::kCsvFields + 1);
  try {
    io::parse_pose_csv(line, "p.csv");
    FAIL("accepted");
  } catch (const Error& e) {
    const std::string msg = e.what();
    CHECK(msg.find("p.csv: line 1: expected 3 values (x, y, yaw), got more than 16") != std::string::npos);
    CHECK(msg.size() < 300);
  }
  CHECK_THROWS_WITH_AS(io::parse_trajectory_csv("step,waypoint,x,y,yaw\n" + line, "t.csv"),
                       doctest::Contains("got more than 16"), Error);
}

TEST_CASE("JSON: a trajectory of more values than the limit is refused while parsing") {
  std::string text = "{\"steps\": [";
  const std::uint64_t steps = io::limits::kJsonValues / 4 + 1;  // 4 values per one-waypoint step
  text.reserve(steps * 16);
  for (std::uint64_t s = 0; s < steps; ++s) text += s ? ",[[1,2,3]]" : "[[1,2,3]]";
  text += "]}";
  CHECK_THROWS_WITH_AS(io::parse_trajectory_json(text, "t.json"), doctest::Contains("more than 4194304 values"), Error);
}

TEST_CASE("config: frames beyond 16x the released model's 512x1024 are refused by name") {
  std::ifstream in(std::string(EPONA_GOLDEN_DEFAULT_DIR) + "/configs.json");
  const auto golden = nlohmann::json::parse(std::string(std::istreambuf_iterator<char>(in), {}));
  auto j = golden;
  j["world_model_config"]["image_size"] = {4096, 8192};  // the red team's config: 2.4 GB, 56 s
  CHECK_THROWS_WITH_AS(io::parse_configs(j.dump(), "big.json"),
                       doctest::Contains("image_size (4096, 8192) is 33554432 pixels per frame, more than the limit of 8388608"),
                       Error);
  j = golden;
  j["dcae"]["image_size"] = {4096, 8192};
  j["dcae"]["config"]["token_size"] = 128 * 256;
  CHECK_THROWS_WITH_AS(io::parse_configs(j.dump(), "big.json"), doctest::Contains("more than the limit of 8388608"), Error);
  j = golden;
  j["world_model_config"]["image_size"] = {2048, 4096};  // at the limit: accepted
  j["dcae"]["image_size"] = {2048, 4096};
  j["dcae"]["config"]["token_size"] = 64 * 128;
  CHECK_NOTHROW(io::parse_configs(j.dump(), "ok.json"));
}

#include "epona/io/stb_implementation.hpp"
