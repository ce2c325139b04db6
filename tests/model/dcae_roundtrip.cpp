// Encode -> decode of a real photograph (tests/data/images, 128x256) through the DC-AE with the
// golden set's (random) weights and config, images in and out through epona/io/image.hpp: shapes,
// finite values, and the written PNG equal, pixel for pixel, to clip(x/2 + 0.5)·255 truncated of
// the decoded tensor. At 128x256 the latent is 4x8 = 32 positions, so the last EViT stages take
// LiteMLA's quadratic order (the golden cases cover the linear one). Random weights reconstruct
// nothing: the figures printed are statistics, not quality. The one TU compiling stb here.
#include <doctest/doctest.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <unistd.h>

#include "epona/cpu/context.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/image.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/io/stb_implementation.hpp"
#include "epona/model/dcae.hpp"
#include "../golden_dir.hpp"

using namespace epona;
using epona::test::golden_dir;
using HostTensor = Tensor<float, Cpu>;

namespace {

bool all_finite(const HostTensor& t) {
  for (std::int64_t i = 0; i < t.numel(); ++i)
    if (!std::isfinite(t.data()[i])) return false;
  return true;
}

}  // namespace

TEST_CASE("photograph -> encode -> decode -> PNG") {
  cpu::Context ctx;
  const auto weights = io::load_safetensors(golden_dir() + "/weights_dcae.safetensors");
  const DcaeConfig config = io::load_configs(golden_dir() + "/configs.json").dcae;
  const auto model = Dcae<Cpu, float>::load(weights, config);

  const std::string photo = std::string(EPONA_TEST_DATA_DIR) + "/images/stm32f3discovery_128x256.jpg";
  const io::Image input = io::read_image(photo, {.height = 128, .width = 256});
  const HostTensor x = io::image_to_tensor(input);
  CHECK(x.shape() == Shape{1, 3, 128, 256});

  const HostTensor z = model.encode(ctx, x);
  CHECK(z.shape() == Shape{1, config.latent_channels, 4, 8});
  CHECK(all_finite(z));

  const HostTensor y = model.decode(ctx, z, false);
  CHECK(y.shape() == Shape{1, 3, 128, 256});
  REQUIRE(all_finite(y));

  const auto out_path = (std::filesystem::temp_directory_path() /
                         ("epona_roundtrip_" + std::to_string(::getpid()) + ".png")).string();
  io::save_png(out_path, y);
  const io::Image written = io::read_image(out_path, {.height = 128, .width = 256});
  std::filesystem::remove(out_path);
  REQUIRE(written.height == 128);
  REQUIRE(written.width == 256);

  std::int64_t mismatches = 0, clipped = 0;
  double abs_diff_to_input = 0, lo = INFINITY, hi = -INFINITY;
  const std::int64_t plane = 128 * 256;
  for (std::int64_t p = 0; p < plane; ++p)
    for (int c = 0; c < 3; ++c) {
      const float v = y.data()[c * plane + p];
      lo = std::min<double>(lo, v), hi = std::max<double>(hi, v);
      const float unit = v / 2.0f + 0.5f;
      clipped += unit < 0.0f || unit > 1.0f;
      const auto expect = static_cast<int>(std::clamp(unit, 0.0f, 1.0f) * 255.0f);
      mismatches += written.rgb[p * 3 + c] != expect;
      abs_diff_to_input += std::abs(int(written.rgb[p * 3 + c]) - int(input.rgb[p * 3 + c]));
    }
  std::printf("round trip (random golden weights): decoded range [%.3f, %.3f], %.1f%% of samples clipped, "
              "mean |PNG - photo| = %.1f levels\n",
              lo, hi, 100.0 * double(clipped) / double(3 * plane), abs_diff_to_input / double(3 * plane));
  CHECK(mismatches == 0);
  CHECK(hi > lo);  // not a constant image

  // The same latent as a clip of condition_frames copies: frame 0 is the single-frame decode.
  const std::int64_t Tc = config.condition_frames;
  HostTensor clip({Tc, z.size(1), z.size(2), z.size(3)});
  for (std::int64_t f = 0; f < Tc; ++f) std::copy_n(z.data(), z.numel(), clip.data() + f * z.numel());
  const HostTensor frames = model.decode(ctx, clip, true);
  CHECK(frames.shape() == Shape{Tc, 3, 128, 256});
  CHECK(all_finite(frames));
  double d0 = 0;
  for (std::int64_t i = 0; i < y.numel(); ++i) d0 = std::max<double>(d0, std::abs(frames.data()[i] - y.data()[i]));
  CHECK(d0 <= 1e-5 * std::max(std::abs(lo), std::abs(hi)));
}
