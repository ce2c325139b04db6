// epona/io/video_writer.hpp — RGB8 frames (io::Image) into an H.264 MP4 through FFmpeg's
// libraries (libavcodec, libavformat, libavutil, libswscale): yuv420p at a fixed frame rate, the
// encoder libx264 when present, else the H.264 encoder libavcodec offers. Self-contained: only
// translation units that include it need those libraries (CMake: link epona_ffmpeg).
//
// The file is written as every output is (io/atomic_file.hpp): into a temporary file beside the
// destination, listed for the program's signal handler, renamed into place by finish(). An error,
// an exception or a writer dropped before finish() leaves no file at the destination.
//
// Frame size: H.264 in 4:2:0 needs an even width and height. An odd side is padded by one pixel
// that repeats the last column (row), so every frame pixel is in the video, which is then one
// pixel wider (taller) than the frames.
#pragma once

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

extern "C" {
#include <libavcodec/avcodec.h>
#include <libavformat/avformat.h>
#include <libavutil/imgutils.h>
#include <libavutil/opt.h>
#include <libswscale/swscale.h>
}

#include "epona/core/error.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/io/image.hpp"

namespace epona::io {

struct VideoOptions {
  int fps = 5;   // frames per second, 1..120 (Epona's data runs at 5 Hz)
  int crf = 18;  // libx264's constant rate factor: 0 lossless .. 51; 18 looks lossless to most eyes
};

inline constexpr int kMaxVideoFps = 120;

namespace video_detail {

// libav's av_err2str is a C compound literal, which C++ lacks.
inline std::string av_error_text(int code) {
  char text[AV_ERROR_MAX_STRING_SIZE] = {};
  if (av_strerror(code, text, sizeof text) < 0) return "libav error " + std::to_string(code);
  return text;
}

// Throws naming the destination, what failed and libav's reason, when `code` is an error.
inline void check_av(int code, const std::string& destination, const char* what) {
  if (code < 0) fail(destination, ": ", what, " failed: ", av_error_text(code));
}

struct FrameDeleter {
  void operator()(AVFrame* f) const { av_frame_free(&f); }
};
struct PacketDeleter {
  void operator()(AVPacket* p) const { av_packet_free(&p); }
};
struct CodecDeleter {
  void operator()(AVCodecContext* c) const { avcodec_free_context(&c); }
};
struct ScaleDeleter {
  void operator()(SwsContext* s) const { sws_freeContext(s); }
};
// Closes the file the muxer writes (if opened) with the context.
struct FormatDeleter {
  void operator()(AVFormatContext* f) const {
    if (f->pb && !(f->oformat->flags & AVFMT_NOFILE)) avio_closep(&f->pb);
    avformat_free_context(f);
  }
};
using FramePtr = std::unique_ptr<AVFrame, FrameDeleter>;
using PacketPtr = std::unique_ptr<AVPacket, PacketDeleter>;
using CodecPtr = std::unique_ptr<AVCodecContext, CodecDeleter>;
using ScalePtr = std::unique_ptr<SwsContext, ScaleDeleter>;
using FormatPtr = std::unique_ptr<AVFormatContext, FormatDeleter>;

inline std::int64_t even(std::int64_t n) { return n + (n & 1); }

// libx264 first (the encoder quality and CRF refer to), then any H.264 encoder of the build.
inline const AVCodec* h264_encoder(const std::string& destination) {
  const AVCodec* codec = avcodec_find_encoder_by_name("libx264");
  if (!codec) codec = avcodec_find_encoder(AV_CODEC_ID_H264);
  EPONA_CHECK(codec != nullptr, destination, ": this FFmpeg (libavcodec ", LIBAVCODEC_IDENT,
              ") has no H.264 encoder; install one built with libx264");
  return codec;
}

inline FramePtr alloc_frame(AVPixelFormat format, std::int64_t height, std::int64_t width, const std::string& destination) {
  FramePtr f(av_frame_alloc());
  EPONA_CHECK(f != nullptr, destination, ": out of memory for a video frame");
  f->format = format;
  f->width = static_cast<int>(width);
  f->height = static_cast<int>(height);
  check_av(av_frame_get_buffer(f.get(), 0), destination, "allocating a video frame");
  return f;
}

}  // namespace video_detail

// Writes frames of one size as they come: add() each, then finish(). Not copyable.
class VideoWriter {
 public:
  // `height` x `width`: the frames' size (an odd side is padded, see above).
  VideoWriter(const std::filesystem::path& path, std::int64_t height, std::int64_t width, const VideoOptions& opt = {})
      : destination_(path.string()), height_(height), width_(width) {
    check_arguments(opt);
    temp_ = std::make_unique<atomic_detail::TempFile>(path);
    open_encoder(opt);
    open_file();
  }
  VideoWriter(const VideoWriter&) = delete;
  VideoWriter& operator=(const VideoWriter&) = delete;

  void add(const Image& img) {
    EPONA_CHECK(!finished_, destination_, ": add() after finish()");
    EPONA_CHECK(img.height == height_ && img.width == width_ &&
                    img.rgb.size() == static_cast<std::size_t>(img.height * img.width * 3),
                destination_, ": frame ", frames_, " is ", img.height, "x", img.width, ", the video's frames are ", height_,
                "x", width_);
    fill_rgb(img);
    video_detail::check_av(av_frame_make_writable(yuv_.get()), destination_, "making a video frame writable");
    const int rows = sws_scale(scale_.get(), rgb_->data, rgb_->linesize, 0, rgb_->height, yuv_->data, yuv_->linesize);
    EPONA_CHECK(rows == yuv_->height, destination_, ": libswscale converted ", rows, " of ", yuv_->height,
                " rows of frame ", frames_, " to yuv420p");
    yuv_->pts = frames_++;
    encode(yuv_.get());
  }

  // Drains the encoder, completes the MP4 and renames it into place. At least one frame is needed.
  void finish() {
    EPONA_CHECK(!finished_, destination_, ": finish() called twice");
    EPONA_CHECK(frames_ > 0, destination_, ": a video needs at least one frame; none was given (nothing written)");
    finished_ = true;
    encode(nullptr);
    video_detail::check_av(av_write_trailer(format_.get()), destination_, "writing the MP4 index (trailer)");
    const int closed = avio_closep(&format_->pb);
    video_detail::check_av(closed, destination_, "closing the video file");
    temp_->sync_and_close(destination_);
    if (::rename(temp_->name().c_str(), destination_.c_str()) != 0)
      fail(destination_, ": cannot rename ", temp_->name(), " into place: ", std::strerror(errno));
    temp_->release();
    atomic_detail::sync_directory(std::filesystem::path(destination_).parent_path());
  }

  std::int64_t frames() const { return frames_; }
  // The encoded size: the frames' size, odd sides padded to even.
  std::int64_t video_height() const { return video_detail::even(height_); }
  std::int64_t video_width() const { return video_detail::even(width_); }
  const char* encoder_name() const { return codec_->codec->name; }

 private:
  void check_arguments(const VideoOptions& opt) const {
    EPONA_CHECK(opt.fps >= 1 && opt.fps <= kMaxVideoFps, destination_, ": frame rate ", opt.fps,
                " fps is outside 1..", kMaxVideoFps);
    EPONA_CHECK(opt.crf >= 0 && opt.crf <= 51, destination_, ": crf ", opt.crf, " is outside libx264's 0..51");
    EPONA_CHECK(height_ > 0 && width_ > 0, destination_, ": frames of ", height_, "x", width_, " cannot make a video");
    EPONA_CHECK(height_ <= 16384 && width_ <= 16384, destination_, ": frames of ", height_, "x", width_,
                " are larger than H.264 takes (16384 per side)");
    std::error_code ec;
    EPONA_CHECK(!std::filesystem::is_directory(destination_, ec), destination_,
                ": is a directory, cannot write a video there");
  }

  void open_encoder(const VideoOptions& opt) {
    const AVCodec* codec = video_detail::h264_encoder(destination_);
    codec_.reset(avcodec_alloc_context3(codec));
    EPONA_CHECK(codec_ != nullptr, destination_, ": out of memory for the H.264 encoder");
    AVCodecContext* c = codec_.get();
    c->width = static_cast<int>(video_width());
    c->height = static_cast<int>(video_height());
    c->time_base = AVRational{1, opt.fps};
    c->framerate = AVRational{opt.fps, 1};
    c->pix_fmt = AV_PIX_FMT_YUV420P;
    c->gop_size = 4 * opt.fps;
    // What libswscale's default RGB -> YUV conversion produces, so players convert back alike.
    c->colorspace = AVCOL_SPC_SMPTE170M;
    c->color_primaries = AVCOL_PRI_SMPTE170M;
    c->color_trc = AVCOL_TRC_SMPTE170M;
    c->color_range = AVCOL_RANGE_MPEG;
    if (std::string(codec->name) == "libx264")
      video_detail::check_av(av_opt_set_int(c->priv_data, "crf", opt.crf, 0), destination_, "setting libx264's crf");
    // MP4 keeps the stream headers once, in the file header, rather than in the stream.
    c->flags |= AV_CODEC_FLAG_GLOBAL_HEADER;
    video_detail::check_av(avcodec_open2(c, codec, nullptr), destination_,
                           (std::string("opening the H.264 encoder ") + codec->name).c_str());
    rgb_ = video_detail::alloc_frame(AV_PIX_FMT_RGB24, video_height(), video_width(), destination_);
    yuv_ = video_detail::alloc_frame(AV_PIX_FMT_YUV420P, video_height(), video_width(), destination_);
    scale_.reset(sws_getContext(c->width, c->height, AV_PIX_FMT_RGB24, c->width, c->height, AV_PIX_FMT_YUV420P,
                                SWS_BICUBIC, nullptr, nullptr, nullptr));
    EPONA_CHECK(scale_ != nullptr, destination_, ": libswscale cannot convert RGB24 to yuv420p at ", c->height, "x",
                c->width);
    packet_.reset(av_packet_alloc());
    EPONA_CHECK(packet_ != nullptr, destination_, ": out of memory for a video packet");
  }

  // The MP4 muxer writes to the temporary file by name (it creates nothing: the file exists).
  void open_file() {
    AVFormatContext* raw = nullptr;
    video_detail::check_av(avformat_alloc_output_context2(&raw, nullptr, "mp4", temp_->name().c_str()), destination_,
                           "setting up the MP4 muxer");
    format_.reset(raw);
    stream_ = avformat_new_stream(raw, nullptr);
    EPONA_CHECK(stream_ != nullptr, destination_, ": out of memory for the video stream");
    stream_->time_base = codec_->time_base;
    stream_->avg_frame_rate = codec_->framerate;
    video_detail::check_av(avcodec_parameters_from_context(stream_->codecpar, codec_.get()), destination_,
                           "describing the video stream");
    video_detail::check_av(avio_open(&raw->pb, temp_->name().c_str(), AVIO_FLAG_WRITE), destination_,
                           "opening the temporary file");
    video_detail::check_av(avformat_write_header(raw, nullptr), destination_, "writing the MP4 header");
  }

  // The frame into the RGB buffer; an odd side's padding repeats the last column (row).
  void fill_rgb(const Image& img) {
    video_detail::check_av(av_frame_make_writable(rgb_.get()), destination_, "making a video frame writable");
    const std::int64_t row_bytes = width_ * 3;
    for (std::int64_t y = 0; y < video_height(); ++y) {
      const std::uint8_t* src = img.rgb.data() + std::min(y, height_ - 1) * row_bytes;
      std::uint8_t* dst = rgb_->data[0] + y * rgb_->linesize[0];
      std::memcpy(dst, src, static_cast<std::size_t>(row_bytes));
      if (video_width() != width_) std::memcpy(dst + row_bytes, src + row_bytes - 3, 3);
    }
  }

  // Sends a frame (nullptr: the end) and writes every packet the encoder has ready.
  void encode(const AVFrame* frame) {
    video_detail::check_av(avcodec_send_frame(codec_.get(), frame), destination_,
                           frame ? "sending a frame to the H.264 encoder" : "flushing the H.264 encoder");
    while (true) {
      const int got = avcodec_receive_packet(codec_.get(), packet_.get());
      if (got == AVERROR(EAGAIN) || got == AVERROR_EOF) return;
      video_detail::check_av(got, destination_, "encoding a frame");
      av_packet_rescale_ts(packet_.get(), codec_->time_base, stream_->time_base);
      packet_->stream_index = stream_->index;
      // av_interleaved_write_frame takes the packet's data and leaves it blank.
      video_detail::check_av(av_interleaved_write_frame(format_.get(), packet_.get()), destination_,
                             "writing to the video file");
    }
  }

  std::string destination_;
  std::int64_t height_, width_;
  // Declared first, so destroyed last: the temporary file is removed after the muxer closes it.
  std::unique_ptr<atomic_detail::TempFile> temp_;
  video_detail::CodecPtr codec_;
  video_detail::FramePtr rgb_, yuv_;
  video_detail::ScalePtr scale_;
  video_detail::PacketPtr packet_;
  video_detail::FormatPtr format_;
  AVStream* stream_ = nullptr;  // owned by format_
  std::int64_t frames_ = 0;
  bool finished_ = false;
};

// All `frames` (one size, at least one) as one MP4 at `path`.
inline void write_video(const std::filesystem::path& path, const std::vector<Image>& frames, const VideoOptions& opt = {}) {
  EPONA_CHECK(!frames.empty(), path.string(), ": a video needs at least one frame; none was given (nothing written)");
  VideoWriter writer(path, frames.front().height, frames.front().width, opt);
  for (const auto& f : frames) writer.add(f);
  writer.finish();
}

}  // namespace epona::io
