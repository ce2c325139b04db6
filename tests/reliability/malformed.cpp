// Issue #36, silent success on malformed input: ZIP entries that overlap in the file (one stretch
// of bytes read under two names, an entry hidden in another's data) and JPEG scans cut short
// before a well-placed end-of-image marker (stb decodes the rest as grey) are refused.
#include <doctest/doctest.h>

#include <string>

#include <cstdint>
#include <utility>
#include <vector>

#include "../io/zip_builder.hpp"
#include "epona/io/image.hpp"
#include "epona/io/zip.hpp"

using namespace epona;

TEST_CASE("zip: entries overlapping in the file are refused") {
  zip_test::ZipSpec s;
  s.entries.push_back({"a", std::string(64, 'a')});
  s.entries.push_back({"b", "hello"});
  s.entries[0].descriptor = true;  // local sizes zero: only the central record says where 'a' ends
  const auto z = zip_test::layout_zip(s);
  std::string bytes = z.bytes();
  CHECK_NOTHROW(zip_test::open_zip(bytes));
  // Stretch 'a' over 'b' (its descriptor, local header and data): both sizes in the central record.
  const auto stretched = static_cast<std::uint32_t>(z.data_offsets[1] + 5 - z.data_offsets[0]);
  zip_test::poke<std::uint32_t>(bytes, z.central_offsets[0] + 20, stretched);
  zip_test::poke<std::uint32_t>(bytes, z.central_offsets[0] + 24, stretched);
  CHECK_THROWS_WITH_AS(zip_test::open_zip(bytes), doctest::Contains("entries 'a' (bytes 0 to"), Error);
  CHECK_THROWS_WITH_AS(zip_test::open_zip(bytes), doctest::Contains("overlap in the file"), Error);
  // Two central records pointing at one local header: refused too (they name different entries).
  std::string twice = z.bytes();
  zip_test::poke<std::uint32_t>(twice, z.central_offsets[1] + 42, static_cast<std::uint32_t>(z.local_offsets[0]));
  CHECK_THROWS_AS(zip_test::open_zip(twice), Error);
}

// ---- JPEG scans cut short (io/jpeg_scan.hpp) -------------------------------------------------

namespace {

std::vector<std::uint8_t> jpeg_of(int w, int h, int quality) {
  std::vector<std::uint8_t> pixels(std::size_t(w) * std::size_t(h) * 3), out;
  for (std::size_t i = 0; i < pixels.size(); ++i) pixels[i] = static_cast<std::uint8_t>((i * 7919) % 251);
  stbi_write_jpg_to_func(
      [](void* ctx, void* data, int n) {
        auto* v = static_cast<std::vector<std::uint8_t>*>(ctx);
        v->insert(v->end(), static_cast<std::uint8_t*>(data), static_cast<std::uint8_t*>(data) + n);
      },
      &out, w, h, 3, pixels.data(), quality);
  return out;
}

// The file with its scan data cut to `keep` of its length, then the end-of-image marker.
std::vector<std::uint8_t> cut_scan(const std::vector<std::uint8_t>& jpg, double keep) {
  std::size_t sos = 0;
  for (std::size_t i = 2; i + 1 < jpg.size(); ++i)
    if (jpg[i] == 0xFF && jpg[i + 1] == 0xDA) sos = i;
  const std::size_t data = sos + 2 + ((std::size_t{jpg[sos + 2]} << 8) | jpg[sos + 3]);
  std::size_t cut = data + static_cast<std::size_t>(double(jpg.size() - 2 - data) * keep);
  if (jpg[cut - 1] == 0xFF) --cut;  // not in the middle of a stuffed 0xFF00
  std::vector<std::uint8_t> out(jpg.begin(), jpg.begin() + static_cast<std::ptrdiff_t>(cut));
  out.push_back(0xFF);
  out.push_back(0xD9);
  return out;
}

}  // namespace

TEST_CASE("jpeg: a scan cut short before an end-of-image marker is refused; whole files pass") {
  for (int quality : {30, 95}) {  // stb subsamples chroma (4:2:0) up to quality 90, not above
    for (auto [w, h] : {std::pair{64, 32}, std::pair{37, 53}}) {
      CAPTURE(quality);
      CAPTURE(w);
      const auto jpg = jpeg_of(w, h, quality);
      io::ImageReadOptions opt;
      opt.size = io::SizePolicy::Resize, opt.height = 32, opt.width = 32;
      CHECK(io::decode_image(jpg, "whole.jpg", opt).width == 32);
      for (double keep : {0.0, 0.3, 0.8}) {
        CAPTURE(keep);
        CHECK_THROWS_WITH_AS(io::decode_image(cut_scan(jpg, keep), "cut.jpg", opt),
                             doctest::Contains("cut.jpg: truncated JPEG (scan 1 ends after"), Error);
      }
    }
  }
}

namespace {

std::size_t scan_data_start(const std::vector<std::uint8_t>& jpg) {
  std::size_t sos = 0;
  for (std::size_t i = 2; i + 1 < jpg.size(); ++i)
    if (jpg[i] == 0xFF && jpg[i + 1] == 0xDA) sos = i;
  return sos + 2 + ((std::size_t{jpg[sos + 2]} << 8) | jpg[sos + 3]);
}

}  // namespace

TEST_CASE("jpeg: bytes between segments are stepped over as stb does, so the scan is still checked") {
  // Finding 11 (docs/reliability.md): junk after a segment made the walk give up, and stb met a
  // scan whose data ran out with undefined behaviour inside it.
  io::ImageReadOptions opt;
  opt.size = io::SizePolicy::Resize, opt.height = 32, opt.width = 32;
  auto jpg = jpeg_of(64, 32, 80);
  const std::vector<std::uint8_t> junk{0x00, 0x01, 0x00, 0x7F};
  jpg.insert(jpg.begin() + 2 + 2 + ((jpg[4] << 8) | jpg[5]), junk.begin(), junk.end());  // after APP0
  CHECK(io::decode_image(jpg, "junk.jpg", opt).width == 32);  // stb reads it: so does epona
  CHECK_THROWS_WITH_AS(io::decode_image(cut_scan(jpg, 0.5), "junk_cut.jpg", opt),
                       doctest::Contains("junk_cut.jpg: truncated JPEG (scan 1 ends after"), Error);
}

TEST_CASE("jpeg: a scan holding a code its Huffman tables lack is refused before stb sees it") {
  io::ImageReadOptions opt;
  opt.size = io::SizePolicy::Resize, opt.height = 32, opt.width = 32;
  auto jpg = jpeg_of(64, 64, 80);
  // No Huffman table holds the 16-bit all-ones code (JPEG reserves it): a run of data bytes 0xFF
  // (stuffed as 0xFF 0x00) is an invalid code wherever the next code begins inside it.
  const std::size_t data = scan_data_start(jpg);
  for (std::size_t i = data + 8; i < data + 40; i += 2) jpg[i] = 0xFF, jpg[i + 1] = 0x00;
  CHECK_THROWS_WITH_AS(io::decode_image(jpg, "bad_code.jpg", opt),
                       doctest::Contains("bad_code.jpg: corrupt JPEG (scan 1, MCU "), Error);
}

TEST_CASE("jpeg: a scan that names a Huffman table the file does not define is refused") {
  // Finding 12 (docs/reliability.md): stb decoded with the undefined table and its bit reader
  // went below zero bits.
  io::ImageReadOptions opt;
  opt.size = io::SizePolicy::Resize, opt.height = 32, opt.width = 32;
  auto jpg = jpeg_of(64, 32, 80);
  // SOS: FF DA, length, Ns = 3, then (id, tables) per component, then 3 bytes before the data.
  const std::size_t sos_tables = scan_data_start(jpg) - 3 - 2 * 3 + 1;  // component 1's table byte
  REQUIRE(jpg[sos_tables - 2] == 3);                                   // Ns
  REQUIRE(jpg[sos_tables - 1] == 1);                                   // component id 1
  jpg[sos_tables] = 0x22;  // DC 2 / AC 2: stb_image_write defines tables 0 and 1 only
  CHECK_THROWS_WITH_AS(io::decode_image(jpg, "undefined_table.jpg", opt),
                       doctest::Contains("undefined_table.jpg: corrupt JPEG (scan 1 codes component 1 with Huffman "
                                         "tables DC 2 and AC 2, and the file does not define the DC one)"),
                       Error);
}

#include "epona/io/stb_implementation.hpp"
