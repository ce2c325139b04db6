// Tests for epona/io/image.hpp: PNG write/read round trip (atomic write, no temporary left),
// JPEG decoding of the committed photograph, the model mapping u -> (u/255 - 0.5)·2 and back
// (clip(x/2 + 0.5) · 255 truncated), every size policy (exact by default, resize, centre crop,
// cover), channel policies (grayscale, RGBA, 16-bit: refused, or converted on request), and
// clear errors for missing, foreign, truncated and corrupt files. This program is the one
// translation unit that compiles stb (epona/io/stb_implementation.hpp).
#include <doctest/doctest.h>

#include "epona/io/image.hpp"

#if defined(STB_IMAGE_IMPLEMENTATION) || defined(STB_IMAGE_WRITE_IMPLEMENTATION)
#error "epona/io/image.hpp must not define the stb implementation macros"
#endif
#include "epona/io/stb_implementation.hpp"

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <unistd.h>

using namespace epona;
using io::Image;
namespace fs = std::filesystem;

namespace {

const std::string kPhoto = std::string(EPONA_TEST_DATA_DIR) + "/images/stm32f3discovery_128x256.jpg";

// A scratch directory removed at exit.
struct Scratch {
  fs::path dir = fs::temp_directory_path() / ("epona_image_test_" + std::to_string(::getpid()));
  Scratch() { fs::create_directories(dir); }
  ~Scratch() {
    std::error_code ec;
    fs::remove_all(dir, ec);
  }
  std::string file(const std::string& name) const { return (dir / name).string(); }
};
const Scratch& scratch() {
  static const Scratch s;
  return s;
}

Image random_image(std::int64_t h, std::int64_t w, std::uint64_t seed) {
  Image img(h, w);
  std::mt19937_64 rng(seed);
  for (auto& v : img.rgb) v = static_cast<std::uint8_t>(rng() & 0xFF);
  return img;
}

void write_bytes(const std::string& path, const std::vector<std::uint8_t>& b) {
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(b.data()), std::streamsize(b.size()));
}
std::vector<std::uint8_t> read_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// A PNG with `comp` 8-bit channels written by stb_image_write.
std::string write_with_channels(const std::string& name, int comp, std::int64_t h, std::int64_t w) {
  std::vector<std::uint8_t> px(static_cast<std::size_t>(h * w * comp));
  for (std::size_t i = 0; i < px.size(); ++i) px[i] = static_cast<std::uint8_t>(i * 7);
  const std::string path = scratch().file(name);
  REQUIRE(stbi_write_png(path.c_str(), int(w), int(h), comp, px.data(), int(w * comp)));
  return path;
}

// A valid 16-bit RGB PNG built by hand (zlib stored blocks, real CRCs and Adler-32).
std::vector<std::uint8_t> png_16bit_rgb(std::uint32_t h, std::uint32_t w) {
  auto crc32 = [](const std::uint8_t* p, std::size_t n) {
    std::uint32_t c = 0xFFFFFFFFu;
    for (std::size_t i = 0; i < n; ++i) {
      c ^= p[i];
      for (int k = 0; k < 8; ++k) c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
    }
    return ~c;
  };
  auto be32 = [](std::vector<std::uint8_t>& v, std::uint32_t x) {
    for (int s = 24; s >= 0; s -= 8) v.push_back(static_cast<std::uint8_t>(x >> s));
  };
  std::vector<std::uint8_t> png = {0x89, 'P', 'N', 'G', 0x0d, 0x0a, 0x1a, 0x0a};
  auto chunk = [&](const char* type, const std::vector<std::uint8_t>& data) {
    be32(png, static_cast<std::uint32_t>(data.size()));
    std::vector<std::uint8_t> body(type, type + 4);
    body.insert(body.end(), data.begin(), data.end());
    png.insert(png.end(), body.begin(), body.end());
    be32(png, crc32(body.data(), body.size()));
  };
  std::vector<std::uint8_t> ihdr;
  be32(ihdr, w), be32(ihdr, h);
  ihdr.insert(ihdr.end(), {16, 2, 0, 0, 0});  // 16-bit, truecolour
  chunk("IHDR", ihdr);
  std::vector<std::uint8_t> raw;
  for (std::uint32_t y = 0; y < h; ++y) {
    raw.push_back(0);
    for (std::uint32_t i = 0; i < w * 6; ++i) raw.push_back(static_cast<std::uint8_t>(y * 31 + i));
  }
  std::vector<std::uint8_t> z = {0x78, 0x01, 0x01};
  const auto len = static_cast<std::uint16_t>(raw.size());
  z.insert(z.end(), {std::uint8_t(len & 0xFF), std::uint8_t(len >> 8), std::uint8_t(~len & 0xFF),
                     std::uint8_t((~len >> 8) & 0xFF)});
  z.insert(z.end(), raw.begin(), raw.end());
  std::uint32_t a = 1, b = 0;
  for (auto v : raw) a = (a + v) % 65521, b = (b + a) % 65521;
  be32(z, (b << 16) | a);
  chunk("IDAT", z);
  chunk("IEND", {});
  return png;
}

}  // namespace

TEST_CASE("PNG round trip is exact and the write is atomic") {
  const Image img = random_image(64, 96, 1);
  const std::string path = scratch().file("round.png");
  io::write_png(path, img);
  const Image back = io::read_image(path);
  CHECK(back.height == 64);
  CHECK(back.width == 96);
  CHECK(back.rgb == img.rgb);
  io::write_png(path, random_image(32, 32, 2));  // overwrites in place
  CHECK(io::read_image(path).width == 32);
  for (const auto& e : fs::directory_iterator(scratch().dir))
    CHECK_MESSAGE(e.path().string().find(".tmp-") == std::string::npos, "left over: " << e.path());
  CHECK_THROWS_WITH_AS(io::write_png(scratch().file("no/such/dir/x.png"), img), doctest::Contains("cannot create the temporary file"),
                       Error);
}

TEST_CASE("the committed photograph decodes as 128x256 RGB") {
  const Image photo = io::read_image(kPhoto, {.height = 128, .width = 256});
  CHECK(photo.height == 128);
  CHECK(photo.width == 256);
  std::array<int, 3> lo{255, 255, 255}, hi{0, 0, 0};
  for (std::int64_t p = 0; p < 128 * 256; ++p)
    for (int c = 0; c < 3; ++c) {
      lo[c] = std::min<int>(lo[c], photo.rgb[p * 3 + c]);
      hi[c] = std::max<int>(hi[c], photo.rgb[p * 3 + c]);
    }
  for (int c = 0; c < 3; ++c) CHECK(hi[c] - lo[c] > 100);  // a real photo, not a flat image
}

TEST_CASE("model mapping: (u/255 - 0.5)·2 in, clip(x/2 + 0.5)·255 truncated out") {
  Image img(1, 3);
  img.rgb = {0, 128, 255, 1, 2, 3, 254, 127, 64};
  const auto t = io::image_to_tensor(img);
  CHECK(t.shape() == Shape{1, 3, 1, 3});
  CHECK(t.at(0, 0, 0, 0) == -1.0f);
  CHECK(t.at(0, 2, 0, 0) == 1.0f);
  CHECK(t.at(0, 1, 0, 0) == (128.0f / 255.0f - 0.5f) * 2.0f);
  CHECK(t.at(0, 0, 0, 2) == (254.0f / 255.0f - 0.5f) * 2.0f);  // channel-major: R of pixel 2
  // Back through the official output mapping: 128 -> 127.99998 -> 127 (truncation), so a uint8
  // image comes back equal or one level lower, never higher.
  const Image back = io::tensor_to_image(t);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) CHECK((back.rgb[i] == img.rgb[i] || back.rgb[i] + 1 == img.rgb[i]));
  CHECK(back.rgb[0] == 0);
  CHECK(back.rgb[2] == 255);

  Tensor<float, Cpu> x({2, 3, 1, 2});
  const float values[12] = {0.f, -1.5f, 2.f, 1.f, -1.f, 0.9999f, 0.5f, -0.25f, 0.f, 0.f, 0.f, 0.f};
  std::copy(values, values + 12, x.data());
  const Image out = io::tensor_to_image(x, 0);
  // x = 0 -> 0.5·255 = 127.5 -> 127 (truncation, not rounding); clipped ends; 0.9999 -> 254.99 -> 254
  CHECK(out.rgb == std::vector<std::uint8_t>{127, 255, 0, 0, 255, 254});
  x.at(1, 2, 0, 1) = NAN;
  CHECK_THROWS_WITH_AS(io::tensor_to_image(x, 1), doctest::Contains("1 non-finite"), Error);
  CHECK_NOTHROW(io::tensor_to_image(x, 0));
}

TEST_CASE("size policies: exact by default, resize, centre crop, cover") {
  const std::string path = scratch().file("odd.png");
  io::write_png(path, random_image(90, 160, 3));
  CHECK_THROWS_WITH_AS(io::read_image(path), doctest::Contains("90x160 is not a multiple of 32"), Error);
  CHECK_THROWS_WITH_AS(io::read_image(path, {.height = 64, .width = 96}),
                       doctest::Contains("image is 90x160 (HxW), the model takes 64x96"), Error);
  CHECK_THROWS_WITH_AS(io::read_image(path, {.height = 60, .width = 96, .size = io::SizePolicy::Resize}),
                       doctest::Contains("not a positive multiple of 32"), Error);
  CHECK_THROWS_WITH_AS(io::read_image(path, {.height = 128, .width = 128, .size = io::SizePolicy::CenterCrop}),
                       doctest::Contains("smaller than the 128x128 crop"), Error);

  const Image src = random_image(90, 160, 3);
  const Image resized = io::read_image(path, {.height = 64, .width = 96, .size = io::SizePolicy::Resize});
  CHECK(resized.rgb == io::resize_bicubic(src, 64, 96).rgb);
  CHECK(resized.height == 64);
  CHECK(resized.width == 96);

  const Image cropped = io::read_image(path, {.height = 64, .width = 96, .size = io::SizePolicy::CenterCrop});
  for (std::int64_t y = 0; y < 64; ++y)  // offsets (90-64)/2 = 13, (160-96)/2 = 32
    for (std::int64_t x = 0; x < 96; ++x)
      for (int c = 0; c < 3; ++c) REQUIRE(cropped.at(y, x, c) == src.at(13 + y, 32 + x, c));

  // cover: scale max(64/90, 96/160) = 0.711 -> 64x114, then the centred 64x96 window
  const Image covered = io::read_image(path, {.height = 64, .width = 96, .size = io::SizePolicy::ResizeCover});
  CHECK(covered.rgb == io::center_crop(io::resize_bicubic(src, 64, 114), 64, 96).rgb);
}

TEST_CASE("bicubic resize: PIL's algorithm against a float64 evaluation of the same filter") {
  // Separable Keys cubic (a = -0.5), support scaled by the shrink factor, weights normalised;
  // like PIL, a horizontal pass rounded and clipped to uint8, then a vertical pass. The
  // implementation's 22-bit fixed-point weights may move a result by 1 level.
  auto keys = [](double x) {
    x = std::abs(x);
    return x < 1 ? (1.5 * x - 2.5) * x * x + 1 : x < 2 ? ((-0.5 * x + 2.5) * x - 4) * x + 2 : 0.0;
  };
  auto pass = [&](const std::vector<double>& in, std::int64_t lines, std::int64_t n_in, std::int64_t n_out,
                  std::int64_t stride_line, std::int64_t stride_sample) {
    // resamples `lines` lines of n_in samples (addressed by the strides) to n_out samples each
    std::vector<double> out(static_cast<std::size_t>(lines * n_out));
    const double scale = double(n_in) / double(n_out), fs = std::max(scale, 1.0);
    for (std::int64_t o = 0; o < n_out; ++o) {
      const double center = (o + 0.5) * scale;
      std::vector<double> w(static_cast<std::size_t>(n_in));
      double total = 0;
      for (std::int64_t i = 0; i < n_in; ++i) total += (w[i] = keys((i + 0.5 - center) / fs));
      for (std::int64_t l = 0; l < lines; ++l) {
        double v = 0;
        for (std::int64_t i = 0; i < n_in; ++i) v += w[i] / total * in[l * stride_line + i * stride_sample];
        out[l * n_out + o] = std::clamp(std::floor(v + 0.5), 0.0, 255.0);
      }
    }
    return out;
  };
  const std::int64_t H = 37, W = 53;
  const Image src = random_image(H, W, 4);
  for (auto [h, w] : {std::pair<std::int64_t, std::int64_t>{16, 24}, {64, 96}, {37, 20}}) {
    INFO(h << "x" << w);
    const Image out = io::resize_bicubic(src, h, w);
    int worst = 0;
    for (int c = 0; c < 3; ++c) {
      std::vector<double> plane(static_cast<std::size_t>(H * W));
      for (std::int64_t i = 0; i < H * W; ++i) plane[i] = src.rgb[i * 3 + c];
      const auto rows = pass(plane, H, W, w, W, 1);                        // (H, w)
      const auto cols = h == H ? rows : pass(rows, w, H, h, 1, w);         // (w, h) when resampled
      for (std::int64_t y = 0; y < h; ++y)
        for (std::int64_t x = 0; x < w; ++x) {
          const double expect = h == H ? cols[y * w + x] : cols[x * h + y];
          worst = std::max(worst, std::abs(int(expect) - int(out.at(y, x, c))));
        }
    }
    CHECK(worst <= 1);
  }
  Image flat(20, 30);
  std::fill(flat.rgb.begin(), flat.rgb.end(), std::uint8_t{77});
  const Image flat2 = io::resize_bicubic(flat, 64, 32);  // normalised weights keep a constant exactly
  CHECK(std::all_of(flat2.rgb.begin(), flat2.rgb.end(), [](std::uint8_t v) { return v == 77; }));
  CHECK(io::resize_bicubic(src, 37, 53).rgb == src.rgb);  // same size: untouched
}

TEST_CASE("channels: grayscale, RGBA and 16-bit are refused by default, converted on request") {
  const std::string gray = write_with_channels("gray.png", 1, 32, 64);
  CHECK_THROWS_WITH_AS(io::read_image(gray), doctest::Contains("1 channel(s) (grayscale), expected RGB"), Error);
  const Image g = io::read_image(gray, {.convert_to_rgb8 = true});
  for (std::int64_t p = 0; p < 32 * 64; ++p) {
    CHECK(g.rgb[p * 3] == static_cast<std::uint8_t>(p * 7));  // replicated
    CHECK(g.rgb[p * 3 + 2] == g.rgb[p * 3]);
  }
  const std::string rgba = write_with_channels("rgba.png", 4, 32, 32);
  CHECK_THROWS_WITH_AS(io::read_image(rgba), doctest::Contains("4 channel(s) (RGBA or CMYK)"), Error);
  const Image a = io::read_image(rgba, {.convert_to_rgb8 = true});
  CHECK(a.rgb[3] == static_cast<std::uint8_t>(4 * 7));  // pixel 1's R: the alpha byte was dropped
  CHECK_THROWS_WITH_AS(io::read_image(write_with_channels("ga.png", 2, 32, 32)),
                       doctest::Contains("(grayscale + alpha)"), Error);

  const std::string deep = scratch().file("deep.png");
  write_bytes(deep, png_16bit_rgb(32, 32));
  CHECK_THROWS_WITH_AS(io::read_image(deep), doctest::Contains("16-bit image"), Error);
  const Image d = io::read_image(deep, {.convert_to_rgb8 = true});
  CHECK(d.at(1, 0, 0) == 31);  // the high byte of the first sample of row 1 (31·256 + 32)
}

TEST_CASE("missing, foreign, truncated and corrupt files are clear errors") {
  CHECK_THROWS_WITH_AS(io::read_image(scratch().file("absent.png")), doctest::Contains("no such image file"), Error);
  const std::string text = scratch().file("text.png");
  write_bytes(text, {'h', 'e', 'l', 'l', 'o'});
  CHECK_THROWS_WITH_AS(io::read_image(text), doctest::Contains("not a PNG or JPEG file"), Error);

  const auto jpg = read_bytes(kPhoto);
  const std::string half_jpg = scratch().file("half.jpg");
  write_bytes(half_jpg, {jpg.begin(), jpg.begin() + static_cast<std::ptrdiff_t>(jpg.size() / 2)});
  CHECK_THROWS_WITH_AS(io::read_image(half_jpg), doctest::Contains("truncated JPEG"), Error);

  const std::string png_path = scratch().file("whole.png");
  io::write_png(png_path, random_image(32, 32, 5));
  const auto png = read_bytes(png_path);
  for (std::size_t cut : {png.size() / 2, png.size() - 1, std::size_t{20}}) {
    INFO("cut at " << cut);
    const std::string part = scratch().file("part.png");
    write_bytes(part, {png.begin(), png.begin() + static_cast<std::ptrdiff_t>(cut)});
    CHECK_THROWS_WITH_AS(io::read_image(part), doctest::Contains("truncated PNG"), Error);
  }
  auto corrupt = png;
  corrupt[16] = corrupt[17] = corrupt[18] = corrupt[19] = 0;  // IHDR width 0
  const std::string bad = scratch().file("bad.png");
  write_bytes(bad, corrupt);
  CHECK_THROWS_WITH_AS(io::read_image(bad), doctest::Contains("cannot decode image"), Error);
}
