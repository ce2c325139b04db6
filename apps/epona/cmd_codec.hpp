// apps/epona/cmd_codec.hpp — `epona encode` (images -> DC-AE latents (N, C, H/32, W/32) as .npy)
// and `epona decode` (such latents -> PNG frames, one by one or as temporal clips, and with
// --video an MP4). Latents are the raw DC-AE values the world model works on (no scaling, no shift).
#pragma once

#include <algorithm>
#include <charconv>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "activity.hpp"
#include "args.hpp"
#include "cmd_common.hpp"
#include "console.hpp"
#include "engine.hpp"
#include "frames.hpp"
#include "models.hpp"
#include "video_output.hpp"
#include "epona/core/printable.hpp"
#include "epona/io/image.hpp"
#include "epona/io/limits.hpp"
#include "epona/io/npy.hpp"

namespace epona::app {

inline ArgParser encode_parser() {
  ArgParser p("epona encode", "IMAGE|DIR... [options]",
              "Encodes images (PNG/JPEG files, or every image of a folder in natural name order) with the\n"
              "DC-AE into latents of shape (N, C, H/32, W/32), written as a float32 .npy. Sizes must be\n"
              "multiples of 32 unless --size and --fit say how to convert them.");
  p.positionals(1, 1000000, "image file(s) or folder(s)");
  add_model_options(p, false, true);
  p.option("size", "HxW", "image size to encode at (with --fit)", "the first image's size")
      .option("fit", "MODE", "images not at that size: exact (refuse), resize, crop, cover", "exact")
      .option("max-pixels", "N", "refuse to encode at a size of more pixels (--size, or the first image's)",
              "8388608 (2048x4096)");
  add_compute_options(p);
  p.option("out", "FILE", "latents file (.npy)", "out/encode/latents.npy", 'o')
      .flag("quiet", "no progress bars or notes on stderr", 'q');
  return p;
}

inline ArgParser decode_parser() {
  ArgParser p("epona decode", "LATENTS.npy [options]",
              "Decodes DC-AE latents (N, C, h, w) (as `epona encode` or `epona generate --latents` write them)\n"
              "into PNG frames of (32h, 32w): frame_0000.png ... in the output folder, and with --video an MP4.");
  p.positionals(1, 1, "latents file");
  add_model_options(p, false, true);
  p.option("decode", "MODE", "clip: clips of the DC-AE's temporal length decoded together (N must be a multiple "
           "of it); frame: each frame alone", "frame")
      .option("max-pixels", "N", "refuse latent grids that decode to larger images", "8388608 (2048x4096)");
  add_video_options(p, "the frames");
  add_compute_options(p);
  add_output_options(p, "out/decode");
  return p;
}

inline std::pair<std::int64_t, std::int64_t> parse_size(const std::string& text,
                                                        std::int64_t max_pixels = io::limits::kPixels) {
  const auto x = text.find('x');
  std::int64_t h = 0, w = 0;
  const bool ok = x != std::string::npos &&
                  std::from_chars(text.data(), text.data() + x, h).ptr == text.data() + x &&
                  std::from_chars(text.data() + x + 1, text.data() + text.size(), w).ptr == text.data() + text.size();
  if (!ok || h <= 0 || w <= 0 || h % io::kImageMultiple || w % io::kImageMultiple)
    usage_fail("--size must be HxW with positive multiples of ", io::kImageMultiple, " (e.g. 512x1024), got '",
               printable(text), "'");
  if (h > io::limits::kImageSide || w > io::limits::kImageSide)
    usage_fail("--size ", h, "x", w, ": a side is longer than the limit of ", io::limits::kImageSide);
  if (h > max_pixels / w)
    usage_fail("--size ", h, "x", w, " is ", h * w, " pixels, more than the limit of ", max_pixels,
               " (--max-pixels raises it)");
  return {h, w};
}

// The image files named on the command line (folders expanded in natural name order).
inline std::vector<std::filesystem::path> expand_inputs(const std::vector<std::string>& args) {
  std::vector<std::filesystem::path> files;
  for (const auto& a : args) {
    std::error_code ec;
    if (std::filesystem::is_directory(a, ec)) {
      const auto in_dir = list_images(a, "input");
      files.insert(files.end(), in_dir.begin(), in_dir.end());
    } else {
      EPONA_CHECK(std::filesystem::is_regular_file(a, ec), "input ", a, ": no such file or folder");
      files.emplace_back(a);
    }
  }
  return files;
}

inline int run_encode(const ParsedArgs& a, const Console& con) {
  const ComputeOptions compute = compute_options(a);
  const ModelFiles files = resolve_models(a, false, true);
  const auto policy = size_policy(a.choice("fit", {"exact", "resize", "crop", "cover"}, "exact"));
  std::int64_t H = 0, W = 0;
  const std::int64_t max_pixels = max_pixels_option(a, io::limits::kCodecPixels);
  if (a.has("size")) std::tie(H, W) = parse_size(*a.get("size"), max_pixels);
  const std::filesystem::path out = a.text("out", "out/encode/latents.npy");
  prepare_output_file(out, "--out " + out.string());
  const auto inputs = expand_inputs(a.positionals());
  EPONA_CHECK(static_cast<std::int64_t>(inputs.size()) <= io::limits::kFrames, "encode: ", inputs.size(),
              " images are more than the limit of ", io::limits::kFrames, " per run (encode them in parts)");
  // Images are read up to the reading limit (they may be resized); the size encoded at is
  // bounded by --max-pixels, checked from the first image before the model loads.
  const std::int64_t read_limit = std::max(io::limits::kPixels, max_pixels);
  std::vector<io::Image> images;
  for (const auto& f : inputs) {
    images.push_back(read_frame(f, H, W, policy, read_limit,
                                a.has("size") ? "; pass --fit resize|crop|cover to convert it to --size"
                                              : "; give --size HxW with --fit resize|crop|cover to convert it"));
    if (H == 0) {  // the first image sets the size
      H = images.back().height, W = images.back().width;
      EPONA_CHECK(H <= max_pixels / W, f.string(), ": encoding at its size ", H, "x", W, " (", H * W,
                  " pixels) is more than the limit of ", max_pixels,
                  " (--max-pixels raises it; or --size HxW with --fit converts the images)");
    }
  }
  const auto engine = make_engine(compute);
  engine->load_dcae(files, con);
  const Activity doing("encoding " + std::to_string(images.size()) + " image(s) of " + std::to_string(H) + "x" +
                       std::to_string(W));
  const Tensor<float> latents = encode_frames(*engine, images, con);
  io::write_npy(out, latents);
  con.out << "encoded " << images.size() << " image(s) of " << H << "x" << W << " into " << out.string()
          << ": latents " << shape_str(latents.shape()) << " float32\n";
  return 0;
}

// Latents worth decoding: at least one frame, and a grid whose images stay within --max-pixels
// (the DC-AE decodes each latent cell into 32x32 pixels), checked before the model loads.
inline void check_latent_grid(const Tensor<float>& latents, const std::string& path, std::int64_t max_pixels) {
  EPONA_CHECK(latents.size(0) >= 1 && latents.size(1) >= 1, path, ": latents of shape ", shape_str(latents.shape()),
              " hold no frames to decode");
  EPONA_CHECK(latents.size(2) >= 1 && latents.size(3) >= 1, path, ": latents of shape ", shape_str(latents.shape()),
              " have an empty grid");
  const std::int64_t cells = max_pixels / (io::kImageMultiple * io::kImageMultiple);
  EPONA_CHECK(latents.size(2) <= cells / latents.size(3), path, ": a ", latents.size(2), "x", latents.size(3),
              " latent grid decodes to ", 32 * latents.size(2), "x", 32 * latents.size(3),
              " images, more than the limit of ", max_pixels, " pixels (--max-pixels raises it)");
}

inline int run_decode(const ParsedArgs& a, const Console& con) {
  const ComputeOptions compute = compute_options(a);
  const ModelFiles files = resolve_models(a, false, true);
  const std::string path = a.positionals().front();
  check_file(path, "latents");
  const Tensor<float> latents = io::read_npy<float>(path).values;
  EPONA_CHECK(latents.dim() == 4, path, ": latents must be (N, C, h, w), got ", shape_str(latents.shape()));
  check_latent_grid(latents, path, max_pixels_option(a, io::limits::kCodecPixels));
  for (std::int64_t i = 0; i < latents.numel(); ++i)
    EPONA_CHECK(std::isfinite(latents.data()[i]), path, ": non-finite latent value at flat index ", i);
  const bool clip_decode = a.choice("decode", {"clip", "frame"}, "frame") == "clip";
  const auto dir = output_dir(a, "out/decode");
  const std::optional<VideoRequest> video_to =
      video_request(a, " (decoding in clips, the former --video flag, is --decode clip)");
  IncompleteMarker incomplete(dir, "epona decode");
  remove_stale_frames(dir, latents.size(0));
  const auto engine = make_engine(compute);
  engine->load_dcae(files, con);
  const DcaeConfig& dc = engine->dcae_config();
  const bool temporal = clip_decode && dc.add_decoder_temporal;
  const std::int64_t N = latents.size(0), group = temporal ? dc.condition_frames : 1;
  EPONA_CHECK(N % group == 0, path, ": ", N, " latents are not whole clips of ", group, " frames (--decode clip)");
  std::optional<VideoOut> mp4;
  if (video_to) mp4.emplace(*video_to, 32 * latents.size(2), 32 * latents.size(3));
  Progress bar(con, "decode  ", N, "frame");
  const Activity doing("decoding " + std::to_string(N) + " frame(s) of " + std::to_string(32 * latents.size(2)) + "x" +
                       std::to_string(32 * latents.size(3)));
  for (std::int64_t first = 0; first < N; first += group) {
    const Tensor<float> images = engine->decode(latents.slice(first, first + group), temporal);
    for (std::int64_t i = 0; i < group; ++i) {
      char name[32];
      std::snprintf(name, sizeof name, "frame_%04lld.png", static_cast<long long>(first + i));
      const io::Image frame = io::tensor_to_image(images, i);
      io::write_png((dir / name).string(), frame);
      if (mp4) mp4->put(frame);
    }
    bar.advance(group);
  }
  const std::string video_line = mp4 ? mp4->finish() : std::string();
  incomplete.done();
  con.out << "decoded " << N << " frame(s) of " << 32 * latents.size(2) << "x" << 32 * latents.size(3) << " into "
          << dir.string() << "/frame_0000.png ...\n";
  if (mp4) con.out << video_line << "\n";
  return 0;
}

}  // namespace epona::app
