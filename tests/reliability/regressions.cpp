// One test per bug the fuzzers found (docs/reliability.md lists them): the behaviour the fixed
// code must have on the input class that triggered it. The triggering inputs themselves are
// replayed by fuzz_replay.cpp from fuzz/regressions/<target>/.
#include <doctest/doctest.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <iterator>
#include <limits>
#include <string>
#include <vector>

#include "epona/io/image.hpp"
#include "epona/io/pickle.hpp"
#include "epona/io/stb_implementation.hpp"

using namespace epona;
using namespace epona::io::pickle;

namespace {

// BINFLOAT: 'G' and the big-endian IEEE double.
std::string binfloat(double v) {
  const auto bits = std::bit_cast<std::uint64_t>(v);
  std::string out = "G";
  for (int i = 7; i >= 0; --i) out += static_cast<char>((bits >> (8 * i)) & 0xff);
  return out;
}
std::string binint1(int v) { return std::string("K") + static_cast<char>(v); }

Document unpickle_string(const std::string& s) {
  return unpickle({reinterpret_cast<const std::byte*>(s.data()), s.size()}, "test.pkl");
}

}  // namespace

// fuzz_pickle, crash-c6f4d41a (fuzz/regressions/pickle/float-dict-key-beyond-int64.pkl): a float
// dict key of 2.4e35 was converted to int64 before its range was checked (UB; UBSan:
// float-cast-overflow). Keys compare as Python's do: 2.0 and 2 are one key; floats beyond int64,
// infinities and NaN are keys of their own.
TEST_CASE("pickle: float dict keys outside the int64 range are keys of their own") {
  const double inf = std::numeric_limits<double>::infinity(), nan = std::numeric_limits<double>::quiet_NaN();
  const std::string pickle = "\x80\x02}(" + binfloat(2.4e35) + binint1(1) + binfloat(-1e300) + binint1(2) +
                             binfloat(inf) + binint1(3) + binfloat(nan) + binint1(4) + binfloat(9.3e18) + binint1(5) +
                             binfloat(2.0) + binint1(6) + binint1(2) + binint1(7) + "u.";
  const Document doc = unpickle_string(pickle);
  REQUIRE(doc.root.kind == Kind::Dict);
  const auto& items = doc.dict(doc.root).items;
  REQUIRE(items.size() == 6);  // 2.0 and 2 are the same key, as in Python
  const double keys[] = {2.4e35, -1e300, inf, nan, 9.3e18, 2.0};
  for (std::size_t i = 0; i < 6; ++i) {
    CAPTURE(i);
    CHECK(items[i].first.kind == Kind::Float);
    CHECK(std::bit_cast<std::uint64_t>(items[i].first.f) == std::bit_cast<std::uint64_t>(keys[i]));
    CHECK(items[i].second.i == (i == 5 ? 7 : static_cast<std::int64_t>(i) + 1));  // {2.0: 6, 2: 7} -> 2.0: 7
  }
}

// fuzz_image, crash-15740 (fuzz/regressions/image/jpeg-dht-more-than-256-codes.jpg.in): stb_image
// 2.27 writes past its Huffman tables when a DHT declares more than 256 codes (ASan/UBSan: index
// 257 out of bounds in stbi__build_huffman). image.hpp now checks every DHT table first; tables
// that break the limit, or do not fit their segment, are refused by name.
TEST_CASE("image: a JPEG Huffman table with more than 256 codes is refused before stb sees it") {
  auto jpeg_with_dht = [](const std::vector<std::uint8_t>& counts, std::size_t symbols) {
    std::vector<std::uint8_t> table = {0x00};  // class 0 (DC), table 0
    table.insert(table.end(), counts.begin(), counts.end());
    table.resize(table.size() + symbols, 0x01);
    const std::size_t len = table.size() + 2;
    std::vector<std::uint8_t> b = {0xFF, 0xD8, 0xFF, 0xC4, std::uint8_t(len >> 8), std::uint8_t(len & 0xff)};
    b.insert(b.end(), table.begin(), table.end());
    const std::uint8_t scan[] = {0xFF, 0xDA, 0x00, 0x08, 0x01, 0x01, 0x00, 0x00, 0x3F, 0x00, 0x12, 0x34, 0xFF, 0xD9};
    b.insert(b.end(), std::begin(scan), std::end(scan));
    return b;
  };
  std::vector<std::uint8_t> counts(16, 0);
  counts[0] = 255, counts[1] = 2;  // 257 codes
  CHECK_THROWS_WITH_AS(io::decode_image(jpeg_with_dht(counts, 257), "dht.jpg"),
                       doctest::Contains("dht.jpg: corrupt JPEG (Huffman table at byte 6 declares 257 codes"), Error);
  counts.assign(16, 255);  // 4080 codes, the most 16 count bytes can declare
  CHECK_THROWS_WITH_AS(io::decode_image(jpeg_with_dht(counts, 4080), "dht.jpg"),
                       doctest::Contains("declares 4080 codes"), Error);
  counts.assign(16, 0);
  counts[0] = 2;  // a valid count whose symbols are missing from the segment
  CHECK_THROWS_WITH_AS(io::decode_image(jpeg_with_dht(counts, 1), "dht.jpg"),
                       doctest::Contains("they must fit in its segment"), Error);
  counts[0] = 1;  // a well-formed table passes the check and reaches stb (which finds no frame header)
  CHECK_THROWS_WITH_AS(io::decode_image(jpeg_with_dht(counts, 1), "dht.jpg"), doctest::Contains("cannot decode image"),
                       Error);
}

// fuzz_image, timeout-1b39fa58 (fuzz/regressions/image/jpeg-89-megapixels-in-973-bytes.jpg.in): 973
// bytes of JPEG declared a 3072 x 28960 image, which stb decoded (filling what the file lacked)
// into 267 MB and the model mapping into 1 GB, for 12 s of CPU under ASan. decode_image now refuses
// images over ImageReadOptions::max_pixels (default 2^25, 8K UHD) before decoding.
TEST_CASE("image: a file declaring more than max_pixels is refused before decoding") {
  std::ifstream in(std::string(EPONA_TEST_DATA_DIR) + "/../../fuzz/corpus/image/rgb_32x32_q30.jpg.in", std::ios::binary);
  std::vector<std::uint8_t> jpeg{std::istreambuf_iterator<char>(in), {}};
  REQUIRE(jpeg.size() > 100);
  jpeg.erase(jpeg.begin());  // the fuzz target's option byte
  CHECK(io::decode_image(jpeg, "ok.jpg").height == 32);

  io::ImageReadOptions small;
  small.max_pixels = 32 * 32 - 1;
  CHECK_THROWS_WITH_AS(io::decode_image(jpeg, "ok.jpg", small),
                       doctest::Contains("ok.jpg: image is 32x32 (1024 pixels), more than the limit of 1023 pixels (ImageReadOptions::max_pixels)"),
                       Error);

  // The same data under a start-of-frame declaring 3072 x 28960: refused at once.
  std::size_t sof = 0;
  while (sof + 8 < jpeg.size() && !(jpeg[sof] == 0xFF && jpeg[sof + 1] == 0xC0)) ++sof;
  REQUIRE(sof + 8 < jpeg.size());
  jpeg[sof + 5] = 0x0C, jpeg[sof + 6] = 0x00;  // height 3072
  jpeg[sof + 7] = 0x71, jpeg[sof + 8] = 0x20;  // width 28960
  CHECK_THROWS_WITH_AS(io::decode_image(jpeg, "bomb.jpg"),
                       doctest::Contains("bomb.jpg: image is 3072x28960 (88965120 pixels), more than"), Error);
}
