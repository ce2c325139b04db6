// apps/epona/video_output.hpp — `--video FILE.mp4` and `--fps N` of generate and decode: the
// options checked before any work (an .mp4 name in a writable folder, a sane frame rate), then the
// frames written as they come (epona/io/video_writer.hpp). A program built without FFmpeg's
// libraries refuses --video up front and says how to get it.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>

#include "args.hpp"
#include "output_paths.hpp"
#include "epona/core/printable.hpp"
#include "epona/io/image.hpp"
#include "epona/io/image_folder.hpp"

#if EPONA_HAS_FFMPEG
extern "C" {
#include <libavutil/log.h>
}
#include "epona/io/video_writer.hpp"
#endif

namespace epona::app {

#if EPONA_HAS_FFMPEG
inline constexpr bool kBuiltWithFfmpeg = true;
#else
inline constexpr bool kBuiltWithFfmpeg = false;
#endif

inline constexpr std::int64_t kDefaultFps = 5;  // Epona's frame rate: its data is sampled at 5 Hz
inline constexpr std::int64_t kMaxFps = 120;

inline void add_video_options(ArgParser& p, const std::string& what) {
  p.option("video", "FILE", "also write " + what + " as an H.264 MP4 video (.mp4; needs a build with FFmpeg)")
      .option("fps", "N", "frame rate of --video, 1.." + std::to_string(kMaxFps), std::to_string(kDefaultFps));
}

struct VideoRequest {
  std::filesystem::path path;
  int fps = kDefaultFps;
};

// --video and --fps, checked before the work starts; none without --video. `hint` ends the
// message for a name that is not .mp4 (decode's old --video flag is now --decode clip).
// `with_ffmpeg`: whether this build can write video (a test gives false to see the refusal in a
// build that has FFmpeg).
inline std::optional<VideoRequest> video_request(const ParsedArgs& a, const std::string& hint = "",
                                                 bool with_ffmpeg = kBuiltWithFfmpeg) {
  const auto fps = a.maybe_integer("fps", 1, kMaxFps);
  if (!a.has("video")) {
    if (fps) usage_fail("--fps sets the frame rate of --video FILE.mp4; give --video too");
    return std::nullopt;
  }
  const std::filesystem::path path = *a.get("video");
  if (!with_ffmpeg)
    fail("--video: this epona was built without FFmpeg (libavcodec); install libavcodec-dev libavformat-dev "
         "libavutil-dev libswscale-dev (scripts/setup.sh) and rebuild");
  if (io::lower_text(path.extension().string()) != ".mp4")
    usage_fail("--video ", printable(path.string()), ": epona writes H.264 in MP4 only; give a file name ending in .mp4",
               hint);
  prepare_output_file(path, "--video " + path.string());
  return VideoRequest{path, static_cast<int>(fps.value_or(kDefaultFps))};
}

#if EPONA_HAS_FFMPEG
// The video being written; put() each frame in order, finish() once at the end.
class VideoOut {
 public:
  VideoOut(const VideoRequest& r, std::int64_t height, std::int64_t width)
      : path_(r.path.string()), fps_(r.fps), writer_(r.path, height, width, options(r)) {}
  void put(const io::Image& img) { writer_.add(img); }
  // Completes the file; returns the summary line ("wrote out.mp4 (8 frames of 64x128, 5 fps, H.264 by libx264)").
  std::string finish() {
    writer_.finish();
    return "wrote " + path_ + " (" + std::to_string(writer_.frames()) + " frame(s) of " +
           std::to_string(writer_.video_height()) + "x" + std::to_string(writer_.video_width()) + ", " +
           std::to_string(fps_) + " fps, H.264 by " + writer_.encoder_name() + ")";
  }

 private:
  static io::VideoOptions options(const VideoRequest& r) {
    // libx264 prints its statistics at the info level; the program says what it wrote itself.
    if (av_log_get_level() == AV_LOG_INFO) av_log_set_level(AV_LOG_ERROR);
    io::VideoOptions o;
    o.fps = r.fps;
    return o;
  }

  std::string path_;
  int fps_;
  io::VideoWriter writer_;
};
#else
// Never made: video_request refuses --video in a build without FFmpeg.
class VideoOut {
 public:
  VideoOut(const VideoRequest&, std::int64_t, std::int64_t) { fail("--video: this epona was built without FFmpeg"); }
  void put(const io::Image&) {}
  std::string finish() { return {}; }
};
#endif

}  // namespace epona::app
