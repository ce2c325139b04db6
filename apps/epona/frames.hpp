// apps/epona/frames.hpp — the input clip of plan/generate: a folder of frames (PNG/JPEG, in
// natural name order) and a poses file with one motion per frame; the last F frames of the
// model's window are fitted to the model's image size and encoded (model::make_window, in
// domain/world_session.hpp, makes the window from them).
#pragma once

#include <algorithm>
#include <cctype>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "activity.hpp"
#include "console.hpp"
#include "engine.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cpu/context.hpp"
#include "epona/domain/poses.hpp"
#include "epona/io/image.hpp"
#include "epona/io/image_folder.hpp"
#include "epona/io/limits.hpp"

namespace epona::app {

using io::is_image_file;
using io::lower_text;
using io::natural_less;

// The image files of a folder in natural name order; errors name the folder.
inline std::vector<std::filesystem::path> list_images(const std::filesystem::path& dir, const std::string& option) {
  std::vector<std::filesystem::path> files = io::image_files(dir, option);
  EPONA_CHECK(!files.empty(), option, " ", dir.string(), ": no .png/.jpg/.jpeg frames in the folder");
  return files;
}

inline io::SizePolicy size_policy(const std::string& name) {
  if (name == "resize") return io::SizePolicy::Resize;
  if (name == "crop") return io::SizePolicy::CenterCrop;
  if (name == "cover") return io::SizePolicy::ResizeCover;
  return io::SizePolicy::Exact;
}

// Reads a frame, converting grayscale/RGBA/16-bit to 8-bit RGB and fitting it to height x width.
// The library's size errors name its types (SizePolicy::Resize, "a resize or crop policy"); the
// user knows the options, --fit and (for encode) --size.
inline std::string in_option_words(std::string what, const std::string& fit_hint) {
  const auto replace = [&](const std::string& from, const std::string& to) {
    if (const auto at = what.find(from); at != std::string::npos) what.replace(at, from.size(), to);
  };
  replace("; choose SizePolicy::Resize, CenterCrop or ResizeCover to convert it", fit_hint);
  replace("; ask for a target size with a resize or crop policy", "; give --size HxW with --fit resize|crop|cover");
  return what;
}

inline io::Image read_frame(const std::filesystem::path& file, std::int64_t height, std::int64_t width,
                            io::SizePolicy policy, std::int64_t max_pixels = io::limits::kPixels,
                            const std::string& fit_hint = "; pass --fit resize|crop|cover to convert it") {
  io::ImageReadOptions opt;
  opt.height = height, opt.width = width, opt.size = policy, opt.convert_to_rgb8 = true, opt.max_pixels = max_pixels;
  const Activity doing("reading " + file.string());
  try {
    return io::read_image(file.string(), opt);
  } catch (const Error& e) {
    const std::string what = in_option_words(e.what(), fit_hint);
    if (what != e.what()) fail(what);
    if (what.find("pixels") != std::string::npos && what.find("limit") != std::string::npos)
      fail(what, "; --max-pixels raises the limit");
    throw;
  }
}

// The frames and motions of the model's window.
struct Clip {
  std::vector<std::filesystem::path> files;  // the frames used (the last F of the folder)
  std::vector<io::Image> frames;             // fitted to the model's image size
  io::PoseSequence poses;                    // motion into each frame used
  std::int64_t folder_frames = 0;            // frames in the folder
};

// The last `window` of `files` (at least that many, one pose each, checked by the caller), read
// and fitted to the model's size, and their poses.
inline Clip window_clip(const std::vector<std::filesystem::path>& files, const io::PoseSequence& poses,
                        std::int64_t window, std::int64_t height, std::int64_t width, io::SizePolicy policy,
                        std::int64_t max_pixels = io::limits::kPixels) {
  const auto n = static_cast<std::int64_t>(files.size());
  Clip c;
  c.folder_frames = n;
  for (std::int64_t i = n - window; i < n; ++i) {
    c.files.push_back(files[static_cast<std::size_t>(i)]);
    c.frames.push_back(read_frame(files[static_cast<std::size_t>(i)], height, width, policy, max_pixels));
  }
  c.poses = poses.slice(static_cast<std::size_t>(n - window), static_cast<std::size_t>(window));
  return c;
}

inline Clip load_clip(const std::filesystem::path& frames_dir, const std::filesystem::path& poses_file,
                      std::int64_t window, std::int64_t height, std::int64_t width, io::SizePolicy policy,
                      std::int64_t max_pixels = io::limits::kPixels) {
  const auto files = list_images(frames_dir, "--frames");
  const io::PoseSequence poses = io::load_poses(poses_file);
  const auto n = static_cast<std::int64_t>(files.size());
  EPONA_CHECK(n >= window, "--frames ", frames_dir.string(), ": the model needs ", window,
              " condition frames, the folder holds ", n);
  EPONA_CHECK(static_cast<std::int64_t>(poses.size()) == n, "--poses ", poses_file.string(), " holds ", poses.size(),
              " pose(s) for the ", n, " frame(s) in ", frames_dir.string(), "; give one pose per frame");
  return window_clip(files, poses, window, height, width, policy, max_pixels);
}

// Encodes frames one by one (progress per frame) -> latents (N, C, h, w) on the host.
inline Tensor<float> encode_frames(Engine& engine, const std::vector<io::Image>& frames, const Console& con) {
  Progress bar(con, "encode  ", static_cast<std::int64_t>(frames.size()), "frame");
  Tensor<float> out;
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const Tensor<float> z = engine.encode(frames[i]);  // (1, C, h, w)
    if (out.empty()) out = Tensor<float>({static_cast<std::int64_t>(frames.size()), z.size(1), z.size(2), z.size(3)});
    check_shape(z, {1, out.size(1), out.size(2), out.size(3)}, "encoded frame");
    std::copy_n(z.data(), z.numel(), out[static_cast<std::int64_t>(i)].data());
    bar.advance();
  }
  return out;
}

}  // namespace epona::app
