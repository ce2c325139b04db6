// Reads a video file back for the tests of video writing: the stream's codec, size and frame rate
// as libavformat reports them, and every frame decoded (libavcodec) and converted to RGB8
// (libswscale, its default BT.601 conversion, as the writer's). Errors throw epona::Error.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

extern "C" {
#include <libavcodec/avcodec.h>
#include <libavformat/avformat.h>
#include <libswscale/swscale.h>
}

#include "epona/core/error.hpp"
#include "epona/io/image.hpp"
#include "epona/io/video_writer.hpp"

namespace epona::test {

struct DecodedVideo {
  AVCodecID codec = AV_CODEC_ID_NONE;
  std::int64_t height = 0, width = 0;
  AVRational frame_rate{0, 1};
  AVPixelFormat pixel_format = AV_PIX_FMT_NONE;
  std::vector<io::Image> frames;
};

namespace video_reading_detail {

struct InputDeleter {
  void operator()(AVFormatContext* f) const { avformat_close_input(&f); }
};

inline io::Image to_rgb(const AVFrame* f) {
  std::unique_ptr<SwsContext, io::video_detail::ScaleDeleter> sws(
      sws_getContext(f->width, f->height, static_cast<AVPixelFormat>(f->format), f->width, f->height, AV_PIX_FMT_RGB24,
                     SWS_BICUBIC, nullptr, nullptr, nullptr));
  EPONA_CHECK(sws != nullptr, "test: no RGB conversion of the decoded frame");
  io::Image img(f->height, f->width);
  std::uint8_t* dst[4] = {img.rgb.data(), nullptr, nullptr, nullptr};
  const int stride[4] = {static_cast<int>(img.width * 3), 0, 0, 0};
  sws_scale(sws.get(), f->data, f->linesize, 0, f->height, dst, stride);
  return img;
}

}  // namespace video_reading_detail

inline DecodedVideo read_video(const std::string& path) {
  using io::video_detail::check_av;
  AVFormatContext* raw = nullptr;
  check_av(avformat_open_input(&raw, path.c_str(), nullptr, nullptr), path, "opening the video");
  std::unique_ptr<AVFormatContext, video_reading_detail::InputDeleter> in(raw);
  check_av(avformat_find_stream_info(raw, nullptr), path, "reading the stream information");
  const int index = av_find_best_stream(raw, AVMEDIA_TYPE_VIDEO, -1, -1, nullptr, 0);
  check_av(index, path, "finding the video stream");
  const AVStream* stream = raw->streams[index];
  DecodedVideo v;
  v.codec = stream->codecpar->codec_id;
  v.height = stream->codecpar->height, v.width = stream->codecpar->width;
  v.frame_rate = stream->avg_frame_rate;
  v.pixel_format = static_cast<AVPixelFormat>(stream->codecpar->format);

  const AVCodec* decoder = avcodec_find_decoder(v.codec);
  EPONA_CHECK(decoder != nullptr, path, ": no decoder for the stream");
  io::video_detail::CodecPtr dec(avcodec_alloc_context3(decoder));
  check_av(avcodec_parameters_to_context(dec.get(), stream->codecpar), path, "configuring the decoder");
  check_av(avcodec_open2(dec.get(), decoder, nullptr), path, "opening the decoder");
  io::video_detail::PacketPtr packet(av_packet_alloc());
  io::video_detail::FramePtr frame(av_frame_alloc());
  const auto drain = [&] {
    while (true) {
      const int got = avcodec_receive_frame(dec.get(), frame.get());
      if (got == AVERROR(EAGAIN) || got == AVERROR_EOF) return;
      check_av(got, path, "decoding a frame");
      v.frames.push_back(video_reading_detail::to_rgb(frame.get()));
    }
  };
  while (av_read_frame(raw, packet.get()) >= 0) {
    if (packet->stream_index == index) check_av(avcodec_send_packet(dec.get(), packet.get()), path, "sending a packet");
    av_packet_unref(packet.get());
    drain();
  }
  check_av(avcodec_send_packet(dec.get(), nullptr), path, "flushing the decoder");
  drain();
  return v;
}

}  // namespace epona::test
