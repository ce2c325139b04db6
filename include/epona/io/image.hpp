// epona/io/image.hpp — frames in and out of the DC-AE: PNG/JPEG decoding through stb_image
// (declarations only: include epona/io/stb_implementation.hpp in exactly one translation unit,
// or link a compiled stb such as Debian's libstb), explicit size/channel policies, the model's
// [-1, 1] NCHW float mapping in both directions as Epona's scripts do, and atomic PNG writes.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#if __has_include(<stb/stb_image.h>)
#include <stb/stb_image.h>
#include <stb/stb_image_write.h>
#else
#include <stb_image.h>
#include <stb_image_write.h>
#endif

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/io/jpeg_scan.hpp"
#include "epona/io/limits.hpp"

namespace epona::io {

// 8-bit RGB, row-major (height, width, 3).
struct Image {
  std::int64_t height = 0, width = 0;
  std::vector<std::uint8_t> rgb;

  Image() = default;
  Image(std::int64_t h, std::int64_t w) : height(h), width(w), rgb(static_cast<std::size_t>(h * w * 3)) {}
  std::uint8_t& at(std::int64_t y, std::int64_t x, int c) { return rgb[static_cast<std::size_t>((y * width + x) * 3 + c)]; }
  std::uint8_t at(std::int64_t y, std::int64_t x, int c) const {
    return rgb[static_cast<std::size_t>((y * width + x) * 3 + c)];
  }
};

// What to do when a file is not the size the model takes.
enum class SizePolicy {
  Exact,        // default: a different size is an error naming both sizes
  Resize,       // resize straight to the target (aspect ratio not kept; Epona's nuPlan loader)
  CenterCrop,   // cut the centred target window (the image must be at least that large)
  ResizeCover,  // resize keeping the aspect ratio so the target is covered, then centre-crop (nuScenes)
};

struct ImageReadOptions {
  // Target size; 0 x 0 keeps the file's size, which must then be a multiple of 32 per side.
  std::int64_t height = 0, width = 0;
  SizePolicy size = SizePolicy::Exact;
  // false (default): only 8-bit RGB files are accepted. true: grayscale is replicated to RGB,
  // an alpha channel is dropped (not composited), 16-bit samples keep their high byte.
  bool convert_to_rgb8 = false;
  // Files declaring more pixels are refused before decoding: a few hundred bytes of JPEG can
  // declare a 28960 x 3072 image (a decompression bomb, found by fuzz/fuzz_image). 2^25 holds 8K UHD.
  // Resizing keeps its intermediate image under the same bound.
  std::int64_t max_pixels = limits::kPixels;
  // Either side longer than this is refused too: a 1 x 16.7M strip is within max_pixels, but its
  // resampling weights (taps grow with the scale) and any resize through it are not.
  std::int64_t max_side = limits::kImageSide;
};

inline constexpr std::int64_t kImageMultiple = 32;  // the DC-AE's total downsampling

namespace image_detail {

inline std::vector<std::uint8_t> read_file(const std::string& path) {
  std::error_code ec;
  EPONA_CHECK(std::filesystem::is_regular_file(path, ec), path, ": no such image file");
  std::ifstream in(path, std::ios::binary);
  EPONA_CHECK(in, path, ": cannot open image file");
  std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EPONA_CHECK(!in.bad(), path, ": read error");
  return bytes;
}

inline std::uint32_t be32(const std::uint8_t* p) {
  return (std::uint32_t(p[0]) << 24) | (std::uint32_t(p[1]) << 16) | (std::uint32_t(p[2]) << 8) | p[3];
}

// stb_image 2.27 (Debian 12's libstb) does not bound the code count of a JPEG Huffman table
// (DHT) and writes past its tables when a hostile file declares more than 256 codes (found by
// fuzz/fuzz_image), so every marker segment is walked and every DHT table checked first.
inline void check_jpeg_huffman_tables(std::span<const std::uint8_t> b, const std::string& source) {
  for (std::size_t pos = 2; pos + 1 < b.size();) {
    const std::uint8_t m = b[pos + 1];
    // Scan data, fill bytes, stuffed 0xFF00, RSTn and TEM carry no segment: step over them.
    if (b[pos] != 0xFF || m == 0xFF || m == 0x00 || m == 0x01 || (m >= 0xD0 && m <= 0xD7)) {
      pos += b[pos] == 0xFF && m != 0xFF ? 2 : 1;
      continue;
    }
    if (m == 0xD9) return;  // end of image
    EPONA_CHECK(pos + 4 <= b.size(), source, ": truncated JPEG (marker at byte ", pos, " has no length)");
    const std::size_t len = (std::size_t{b[pos + 2]} << 8) | b[pos + 3];
    EPONA_CHECK(len >= 2 && pos + 2 + len <= b.size(), source, ": corrupt JPEG (the segment at byte ", pos,
                " declares ", len, " bytes, the file ends at ", b.size(), ")");
    for (std::size_t t = pos + 4, end = pos + 2 + len; m == 0xC4 && t < end;) {  // DHT: tables back to back
      EPONA_CHECK(end - t >= 17, source, ": corrupt JPEG (Huffman table at byte ", t, " is cut short)");
      std::size_t codes = 0;
      for (std::size_t i = 1; i <= 16; ++i) codes += b[t + i];
      EPONA_CHECK(codes <= 256 && end - t - 17 >= codes, source, ": corrupt JPEG (Huffman table at byte ", t,
                  " declares ", codes, " codes; at most 256, and they must fit in its segment)");
      t += 17 + codes;
    }
    pos += 2 + len;
  }
}

// stb decodes many truncated files into partly grey images without complaint, so the
// container is checked first: PNG chunks must lie inside the file up to IEND; a JPEG must have
// its end-of-image marker after the last start-of-scan (markers never occur inside scan data).
// decode_image then checks, once the size is known to be within limits, that a sequential JPEG's
// scans hold all their blocks (jpeg_scan.hpp: a scan cut short before a well-placed end-of-image
// marker passed every other check).
inline void check_container(std::span<const std::uint8_t> b, const std::string& source) {
  static constexpr std::uint8_t png_sig[8] = {0x89, 'P', 'N', 'G', 0x0d, 0x0a, 0x1a, 0x0a};
  if (b.size() >= 8 && std::equal(png_sig, png_sig + 8, b.begin())) {
    std::size_t pos = 8;
    while (true) {
      EPONA_CHECK(pos + 12 <= b.size(), source, ": truncated PNG (file ends at byte ", b.size(), " before IEND)");
      const std::uint64_t len = be32(&b[pos]);
      const std::string type(reinterpret_cast<const char*>(&b[pos + 4]), 4);
      EPONA_CHECK(pos + 12 + len <= b.size(), source, ": truncated PNG (chunk '", type, "' at byte ", pos,
                  " needs ", len, " bytes, the file ends at ", b.size(), ")");
      if (type == "IEND") return;
      pos += 12 + len;
    }
  }
  if (b.size() >= 3 && b[0] == 0xFF && b[1] == 0xD8 && b[2] == 0xFF) {
    std::size_t last_sos = 0, last_eoi = 0;
    for (std::size_t i = 2; i + 1 < b.size(); ++i) {
      if (b[i] != 0xFF) continue;
      if (b[i + 1] == 0xDA) last_sos = i;
      if (b[i + 1] == 0xD9) last_eoi = i;
    }
    EPONA_CHECK(last_sos > 0, source, ": JPEG without image data (no start-of-scan marker)");
    EPONA_CHECK(last_eoi > last_sos, source, ": truncated JPEG (no end-of-image marker after the last scan)");
    check_jpeg_huffman_tables(b, source);
    return;
  }
  fail(source, ": not a PNG or JPEG file");
}

inline const char* channel_name(int comp) {
  switch (comp) {
    case 1: return "grayscale";
    case 2: return "grayscale + alpha";
    case 4: return "RGBA or CMYK";
    default: return "RGB";
  }
}

// PIL's bicubic kernel (Keys, a = -0.5), support 2.
inline double bicubic(double x) {
  constexpr double a = -0.5;
  x = std::abs(x);
  if (x < 1.0) return ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0;
  if (x < 2.0) return (((x - 5.0) * x + 8.0) * x - 4.0) * a;
  return 0.0;
}

// One resampling pass along an axis of `in_size` samples to `out_size`, with PIL's algorithm:
// kernel widened by the scale when shrinking (antialiasing), weights normalised to sum 1 and
// stored as 22-bit fixed point, rounding by +2^21, result clamped to [0, 255].
struct AxisWeights {
  std::vector<std::int64_t> first, count;
  std::vector<std::int32_t> weights;  // out_size x taps
  std::int64_t taps = 0;
};

inline AxisWeights axis_weights(std::int64_t in_size, std::int64_t out_size) {
  constexpr int precision_bits = 22;
  const double scale = double(in_size) / double(out_size), filter_scale = std::max(scale, 1.0);
  const double support = 2.0 * filter_scale;
  AxisWeights w;
  w.taps = static_cast<std::int64_t>(std::ceil(support)) * 2 + 1;
  w.first.resize(static_cast<std::size_t>(out_size));
  w.count.resize(static_cast<std::size_t>(out_size));
  w.weights.assign(static_cast<std::size_t>(out_size * w.taps), 0);
  std::vector<double> k(static_cast<std::size_t>(w.taps));
  for (std::int64_t o = 0; o < out_size; ++o) {
    const double center = (double(o) + 0.5) * scale;
    const std::int64_t lo = std::max<std::int64_t>(static_cast<std::int64_t>(center - support + 0.5), 0);
    const std::int64_t hi = std::min<std::int64_t>(static_cast<std::int64_t>(center + support + 0.5), in_size);
    double total = 0;
    for (std::int64_t i = lo; i < hi; ++i) total += (k[i - lo] = bicubic((double(i) - center + 0.5) / filter_scale));
    for (std::int64_t i = lo; i < hi; ++i) {
      const double v = total != 0.0 ? k[i - lo] / total : k[i - lo];
      w.weights[o * w.taps + (i - lo)] = static_cast<std::int32_t>(v < 0 ? -0.5 + v * (1 << precision_bits)
                                                                         : 0.5 + v * (1 << precision_bits));
    }
    w.first[o] = lo, w.count[o] = hi - lo;
  }
  return w;
}

// Resamples along x (horizontal = true) or y of an RGB image.
inline Image resample_axis(const Image& in, std::int64_t out_size, bool horizontal) {
  const std::int64_t in_size = horizontal ? in.width : in.height;
  const AxisWeights w = axis_weights(in_size, out_size);
  Image out(horizontal ? in.height : out_size, horizontal ? out_size : in.width);
  for (std::int64_t y = 0; y < out.height; ++y)
    for (std::int64_t x = 0; x < out.width; ++x) {
      const std::int64_t o = horizontal ? x : y;
      for (int c = 0; c < 3; ++c) {
        std::int64_t acc = std::int64_t{1} << 21;
        for (std::int64_t t = 0; t < w.count[o]; ++t) {
          const std::int64_t i = w.first[o] + t;
          acc += std::int64_t{horizontal ? in.at(y, i, c) : in.at(i, x, c)} * w.weights[o * w.taps + t];
        }
        out.at(y, x, c) = static_cast<std::uint8_t>(std::clamp<std::int64_t>(acc >> 22, 0, 255));
      }
    }
  return out;
}

}  // namespace image_detail

// Resize with PIL's Image.resize(..., BICUBIC) algorithm (horizontal pass, then vertical, each
// skipped when its size is unchanged; see resample_axis). Epona's nuPlan loader uses PIL bicubic.
// The intermediate image (in.height x width) must hold at most `max_pixels`; when only the other
// order fits (a tall strip widened: 16.7M x 1 -> 512 x 1024 went through 16.7M x 1024), the
// vertical pass runs first (PIL's order, and so its exact bytes, are kept whenever they fit).
inline Image resize_bicubic(const Image& in, std::int64_t height, std::int64_t width,
                            std::int64_t max_pixels = limits::kPixels) {
  EPONA_CHECK(height > 0 && width > 0 && in.height > 0 && in.width > 0, "resize_bicubic: cannot resize ", in.height,
              "x", in.width, " to ", height, "x", width);
  const auto fits = [&](std::int64_t h, std::int64_t w) { return h <= max_pixels / w; };
  EPONA_CHECK(fits(height, width), "resize_bicubic: a ", height, "x", width, " image is more than the limit of ",
              max_pixels, " pixels");
  const bool horizontal_first = width == in.width || height == in.height || fits(in.height, width);
  EPONA_CHECK(horizontal_first || fits(height, in.width), "resize_bicubic: resizing ", in.height, "x", in.width,
              " to ", height, "x", width, " needs an intermediate of more than the limit of ", max_pixels, " pixels");
  Image out = in;
  if (horizontal_first) {
    if (width != in.width) out = image_detail::resample_axis(out, width, true);
    if (height != in.height) out = image_detail::resample_axis(out, height, false);
  } else {
    out = image_detail::resample_axis(out, height, false);
    out = image_detail::resample_axis(out, width, true);
  }
  return out;
}

// The centred height x width window; offsets (H - height) / 2 and (W - width) / 2 rounded down.
inline Image center_crop(const Image& in, std::int64_t height, std::int64_t width) {
  EPONA_CHECK(height > 0 && width > 0 && height <= in.height && width <= in.width, "center_crop: a ", height, "x",
              width, " window does not fit in a ", in.height, "x", in.width, " image");
  const std::int64_t top = (in.height - height) / 2, left = (in.width - width) / 2;
  Image out(height, width);
  for (std::int64_t y = 0; y < height; ++y)
    std::memcpy(&out.at(y, 0, 0), in.rgb.data() + ((top + y) * in.width + left) * 3, static_cast<std::size_t>(width * 3));
  return out;
}

// Applies a size policy (see SizePolicy); `source` names the image in errors.
inline Image fit_image(Image img, std::int64_t height, std::int64_t width, SizePolicy policy,
                       const std::string& source = "image", std::int64_t max_pixels = limits::kPixels) {
  if (height == 0 && width == 0) {
    EPONA_CHECK(img.height % kImageMultiple == 0 && img.width % kImageMultiple == 0, source, ": size ", img.height,
                "x", img.width, " is not a multiple of ", kImageMultiple,
                " per side (the DC-AE downsamples 32x); ask for a target size with a resize or crop policy");
    return img;
  }
  EPONA_CHECK(height > 0 && width > 0 && height % kImageMultiple == 0 && width % kImageMultiple == 0, source,
              ": target size ", height, "x", width, " is not a positive multiple of ", kImageMultiple);
  if (img.height == height && img.width == width) return img;
  switch (policy) {
    case SizePolicy::Exact:
      fail(source, ": image is ", img.height, "x", img.width, " (HxW), the model takes ", height, "x", width,
           "; choose SizePolicy::Resize, CenterCrop or ResizeCover to convert it");
    case SizePolicy::Resize: return resize_bicubic(img, height, width, max_pixels);
    case SizePolicy::CenterCrop:
      EPONA_CHECK(img.height >= height && img.width >= width, source, ": image is ", img.height, "x", img.width,
                  ", smaller than the ", height, "x", width, " crop");
      return center_crop(img, height, width);
    case SizePolicy::ResizeCover: {
      const double s = std::max(double(height) / double(img.height), double(width) / double(img.width));
      const std::int64_t h = std::max(height, static_cast<std::int64_t>(std::lround(double(img.height) * s)));
      const std::int64_t w = std::max(width, static_cast<std::int64_t>(std::lround(double(img.width) * s)));
      return center_crop(resize_bicubic(img, h, w, max_pixels), height, width);
    }
  }
  fail(source, ": unknown size policy");
}

// Decodes PNG/JPEG bytes and applies the options; `source` names the data in errors.
inline Image decode_image(std::span<const std::uint8_t> bytes, const std::string& source,
                          const ImageReadOptions& opt = {}) {
  EPONA_CHECK(bytes.size() <= static_cast<std::size_t>(INT32_MAX), source, ": image file too large");
  image_detail::check_container(bytes, source);
  const int len = static_cast<int>(bytes.size());
  int w = 0, h = 0, comp = 0;
  EPONA_CHECK(stbi_info_from_memory(bytes.data(), len, &w, &h, &comp), source, ": cannot decode image (",
              stbi_failure_reason(), ")");
  EPONA_CHECK(std::int64_t{w} * h <= opt.max_pixels, source, ": image is ", h, "x", w, " (", std::int64_t{w} * h,
              " pixels), more than the limit of ", opt.max_pixels, " pixels (ImageReadOptions::max_pixels)");
  EPONA_CHECK(h <= opt.max_side && w <= opt.max_side, source, ": image is ", h, "x", w,
              ", a side longer than the limit of ", opt.max_side, " (ImageReadOptions::max_side)");
  if (bytes[0] == 0xFF) check_jpeg_scans_complete(bytes, source);  // check_container: PNG or JPEG
  const bool deep = stbi_is_16_bit_from_memory(bytes.data(), len) != 0;
  if (!opt.convert_to_rgb8) {
    EPONA_CHECK(comp == 3, source, ": image has ", comp, " channel(s) (", image_detail::channel_name(comp),
                "), expected RGB; set convert_to_rgb8 to convert");
    EPONA_CHECK(!deep, source, ": 16-bit image, expected 8-bit; set convert_to_rgb8 to convert");
  }
  std::uint8_t* data = stbi_load_from_memory(bytes.data(), len, &w, &h, &comp, 3);
  EPONA_CHECK(data != nullptr, source, ": cannot decode image (", stbi_failure_reason(), ")");
  Image img(h, w);
  std::memcpy(img.rgb.data(), data, img.rgb.size());
  stbi_image_free(data);
  return fit_image(std::move(img), opt.height, opt.width, opt.size, source, opt.max_pixels);
}

inline Image read_image(const std::string& path, const ImageReadOptions& opt = {}) {
  const auto bytes = image_detail::read_file(path);
  return decode_image(bytes, path, opt);
}

// Writes an 8-bit RGB PNG: encoded in memory, then written atomically (io/atomic_file.hpp: a
// temporary file beside `path`, flushed and renamed over it), so a reader never sees a partial file.
inline void write_png(const std::string& path, const Image& img) {
  EPONA_CHECK(img.height > 0 && img.width > 0 && img.rgb.size() == static_cast<std::size_t>(img.height * img.width * 3),
              path, ": cannot write an empty or inconsistent image (", img.height, "x", img.width, ")");
  EPONA_CHECK(img.height <= INT32_MAX / 3 && img.width <= INT32_MAX / 3, path, ": image too large for PNG");
  std::vector<std::uint8_t> png;
  const auto append = [](void* ctx, void* data, int size) {
    auto* v = static_cast<std::vector<std::uint8_t>*>(ctx);
    v->insert(v->end(), static_cast<std::uint8_t*>(data), static_cast<std::uint8_t*>(data) + size);
  };
  const int w = static_cast<int>(img.width), h = static_cast<int>(img.height);
  EPONA_CHECK(stbi_write_png_to_func(append, &png, w, h, 3, img.rgb.data(), w * 3) != 0, path, ": PNG encoding failed");
  write_atomically(path, std::string_view(reinterpret_cast<const char*>(png.data()), png.size()));
}

// uint8 RGB -> the model's input (1, 3, H, W): x = (u / 255 - 0.5) · 2 in float32, in that order.
inline Tensor<float, Cpu> image_to_tensor(const Image& img) {
  Tensor<float, Cpu> t({1, 3, img.height, img.width});
  const std::int64_t plane = img.height * img.width;
  for (std::int64_t p = 0; p < plane; ++p)
    for (int c = 0; c < 3; ++c)
      t.data()[c * plane + p] = (static_cast<float>(img.rgb[static_cast<std::size_t>(p * 3 + c)]) / 255.0f - 0.5f) * 2.0f;
  return t;
}

// Images of one size -> (N, 3, H, W).
inline Tensor<float, Cpu> images_to_tensor(const std::vector<Image>& imgs) {
  EPONA_CHECK(!imgs.empty(), "images_to_tensor: no images");
  const std::int64_t H = imgs[0].height, W = imgs[0].width;
  Tensor<float, Cpu> t({static_cast<std::int64_t>(imgs.size()), 3, H, W});
  for (std::size_t i = 0; i < imgs.size(); ++i) {
    EPONA_CHECK(imgs[i].height == H && imgs[i].width == W, "images_to_tensor: image ", i, " is ", imgs[i].height, "x",
                imgs[i].width, ", image 0 is ", H, "x", W);
    const auto one = image_to_tensor(imgs[i]);
    std::copy_n(one.data(), one.numel(), t.data() + static_cast<std::int64_t>(i) * one.numel());
  }
  return t;
}

// Decoder output (N, 3, H, W) [image `index`] or (3, H, W) -> uint8 RGB as Epona's scripts save
// it: v = clip(x / 2 + 0.5, 0, 1), u = truncation of v · 255 (not rounding). Non-finite values
// are an error (they mean the decode failed), not silently mapped.
inline Image tensor_to_image(const Tensor<float, Cpu>& t, std::int64_t index = 0) {
  const bool batched = t.dim() == 4;
  EPONA_CHECK((batched || t.dim() == 3) && t.size(batched ? 1 : 0) == 3, "tensor_to_image: expected (N, 3, H, W) or "
              "(3, H, W), got ", shape_str(t.shape()));
  const Tensor<float, Cpu> one = batched ? t[index] : t;
  const std::int64_t H = one.size(1), W = one.size(2), plane = H * W;
  Image img(H, W);
  std::int64_t bad = 0;
  for (std::int64_t p = 0; p < plane; ++p)
    for (int c = 0; c < 3; ++c) {
      const float x = one.data()[c * plane + p];
      if (!std::isfinite(x)) {
        ++bad;
        continue;
      }
      const float v = std::clamp(x / 2.0f + 0.5f, 0.0f, 1.0f);
      img.rgb[static_cast<std::size_t>(p * 3 + c)] = static_cast<std::uint8_t>(v * 255.0f);
    }
  EPONA_CHECK(bad == 0, "tensor_to_image: ", bad, " non-finite value(s) in the decoded image");
  return img;
}

// Convenience: a file straight to the model's (1, 3, H, W) input, and a decoded image to PNG.
inline Tensor<float, Cpu> load_image_tensor(const std::string& path, const ImageReadOptions& opt = {}) {
  return image_to_tensor(read_image(path, opt));
}
inline void save_png(const std::string& path, const Tensor<float, Cpu>& images, std::int64_t index = 0) {
  write_png(path, tensor_to_image(images, index));
}

}  // namespace epona::io
