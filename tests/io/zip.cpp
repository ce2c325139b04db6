// Tests for epona/io/zip.hpp: archives written by torch.save, Python's zipfile (ZIP64) and the test
// builder, every structural corruption the reader must name, truncations, byte-flip fuzzing, and a
// sparse multi-GB ZIP64 archive with sizes and offsets beyond 4 GiB.
#include "epona/io/zip.hpp"

#include <doctest/doctest.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include "zip_builder.hpp"

using namespace epona;
using namespace epona::io;
using zip_test::layout_zip;
using zip_test::open_zip;
using zip_test::poke;
using zip_test::ZipSpec;

namespace {

const std::string kPklFiles = std::string(EPONA_TEST_DATA_DIR) + "/pkl/";

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  REQUIRE(in.good());
  return {std::istreambuf_iterator<char>(in), {}};
}

std::string as_string(std::span<const std::byte> b) { return {reinterpret_cast<const char*>(b.data()), b.size()}; }

ZipSpec two_entries() {
  ZipSpec s;
  s.entries.push_back({"arc/data.pkl", "pickle bytes"});
  s.entries.push_back({"arc/data/0", std::string(40, 'x')});
  return s;
}

// Expects opening `bytes` to throw epona::Error whose message contains every word.
void expect_zip_error(const std::string& bytes, std::initializer_list<const char*> words) {
  try {
    open_zip(bytes);
    FAIL("opened a corrupt archive; expected an error containing '", *words.begin(), "'");
  } catch (const Error& e) {
    const std::string msg = e.what();
    for (const char* w : words) CHECK_MESSAGE(msg.find(w) != std::string::npos, "'", w, "' not in: ", msg);
    CHECK(msg.find("test.zip") != std::string::npos);  // names the file
  }
}

}  // namespace

TEST_CASE("crc32 matches the standard check value") {
  const std::string s = "123456789";
  CHECK(crc32({reinterpret_cast<const std::byte*>(s.data()), s.size()}) == 0xCBF43926u);
  CHECK(crc32({}) == 0u);
  // Incremental == one shot, across the 8-byte blocks of the sliced loop.
  std::string long_text(1000, '\0');
  for (std::size_t i = 0; i < long_text.size(); ++i) long_text[i] = char(i * 7 + 3);
  const auto* p = reinterpret_cast<const std::byte*>(long_text.data());
  CHECK(crc32({p + 13, 987}, crc32({p, 13})) == crc32({p, 1000}));
}

TEST_CASE("torch.save archives: entries, data descriptors, CRCs agree with miniz") {
  for (const char* f : {"fp32_plain.pkl", "bf16_world.pkl", "views.pkl", "weights_dcae.pkl"}) {
    const auto zip = ZipArchive::open(kPklFiles + f);
    REQUIRE(!zip.entries().empty());
    const std::string stem = std::string(f).substr(0, std::string(f).size() - 4);
    CHECK(zip.entries().front().name == stem + "/data.pkl");
    CHECK(zip.find(stem + "/version") != nullptr);
    for (const auto& e : zip.entries()) {
      CHECK(e.method == 0);
      CHECK(((e.flags & 8) != 0 || e.size == 0));  // torch.save defers CRC and sizes to a data descriptor
      CHECK(zip.data(e).size() == e.size);
      CHECK_NOTHROW(zip.verify_crc(e));  // CRC-32 written by PyTorch's miniz
    }
    CHECK(as_string(zip.data(zip.at(stem + "/version"))).substr(0, 1) == "3");
  }
}

TEST_CASE("ZIP64 archives from Python's zipfile (force_zip64) and hand-built full ZIP64") {
  const auto plain = ZipArchive::open(kPklFiles + "bf16_world.pkl");
  for (const char* f : {"zip64_local.pkl", "zip64_full.pkl"}) {
    const auto zip = ZipArchive::open(kPklFiles + f);
    REQUIRE(zip.entries().size() == plain.entries().size());
    for (std::size_t i = 0; i < zip.entries().size(); ++i) {
      const auto& a = plain.entries()[i];
      const auto& b = zip.entries()[i];
      CHECK(a.name == b.name);
      CHECK(as_string(plain.data(a)) == as_string(zip.data(b)));
      CHECK_NOTHROW(zip.verify_crc(b));
    }
  }
}

TEST_CASE("builder archives: classic, ZIP64, descriptors, comments") {
  for (bool zip64 : {false, true})
    for (bool descriptor : {false, true}) {
      ZipSpec s = two_entries();
      s.zip64 = zip64;
      for (auto& e : s.entries) e.descriptor = descriptor;
      s.comment = zip64 ? "a comment with PK\x05\x06 inside" : "";
      const std::string bytes = layout_zip(s).bytes();
      const auto zip = open_zip(bytes);
      REQUIRE(zip.entries().size() == 2);
      CHECK(as_string(zip.data(zip.at("arc/data.pkl"))) == "pickle bytes");
      CHECK(as_string(zip.data(zip.at("arc/data/0"))) == std::string(40, 'x'));
      CHECK_NOTHROW(zip.verify_crc(zip.at("arc/data/0")));
      CHECK(zip.find("arc/data/1") == nullptr);
      CHECK_THROWS_WITH_AS(zip.at("arc/data/1"), doctest::Contains("no entry 'arc/data/1'"), Error);
    }
  // An empty archive is valid ZIP.
  const std::string empty = layout_zip(ZipSpec{}).bytes();
  CHECK(open_zip(empty).entries().empty());
}

TEST_CASE("compressed and corrupted entries are refused by name") {
  ZipSpec s = two_entries();
  s.entries[1].method = 8;
  const std::string bytes = layout_zip(s).bytes();
  const auto zip = open_zip(bytes);  // listing works; reading the compressed entry does not
  CHECK_THROWS_WITH_AS(zip.data(zip.at("arc/data/0")),
                       doctest::Contains("entry 'arc/data/0' is compressed (method 8, deflate)"), Error);
  CHECK(as_string(zip.data(zip.at("arc/data.pkl"))) == "pickle bytes");

  const auto layout = layout_zip(two_entries());
  std::string corrupt = layout.bytes();
  corrupt[layout.data_offsets[1] + 5] ^= 1;
  const auto z2 = open_zip(corrupt);
  CHECK_THROWS_WITH_AS(z2.verify_crc(z2.at("arc/data/0")), doctest::Contains("'arc/data/0' is corrupt: CRC-32"),
                       Error);
}

TEST_CASE("structural corruptions are named") {
  const auto L = layout_zip(two_entries());
  const std::string good = L.bytes();
  const auto cd0 = L.central_offsets[0], cd1 = L.central_offsets[1];
  auto with = [&](auto&& edit) {
    std::string b = good;
    edit(b);
    return b;
  };

  expect_zip_error("", {"not a ZIP archive", "too small"});
  expect_zip_error("PK\x05\x06", {"too small"});
  expect_zip_error(std::string(100, 'a'), {"not a ZIP archive", "no end-of-central-directory"});
  // End record: bad comment length, split archive, central directory beyond its end.
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, L.eocd_offset + 20, 5); }),
                   {"no end-of-central-directory"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, L.eocd_offset + 4, 1); }), {"multi-disk"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, L.eocd_offset + 16, 1u << 30); }),
                   {"central directory", "overlaps the end records"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, L.eocd_offset + 12, 1000); }),
                   {"overlaps the end records"});
  expect_zip_error(with([&](std::string& b) {
                     poke<std::uint16_t>(b, L.eocd_offset + 8, 3);
                     poke<std::uint16_t>(b, L.eocd_offset + 10, 3);
                   }),
                   {"claims 3 entries"});
  expect_zip_error(with([&](std::string& b) {
                     poke<std::uint16_t>(b, L.eocd_offset + 8, 1);
                     poke<std::uint16_t>(b, L.eocd_offset + 10, 1);
                   }),
                   {"bytes after its last record"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, L.eocd_offset + 16, 0xffffffffu); }),
                   {"needs ZIP64 values", "no ZIP64 end-record locator"});
  // Central directory records.
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, cd1, 0x12345678u); }),
                   {"central directory record 1", "bad signature"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, cd1 + 28, 200); }),
                   {"central directory record 1", "runs past the end"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, cd0 + 8, 1); }),
                   {"'arc/data.pkl' is encrypted"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, cd1 + 42, 1u << 31); }),
                   {"local header of 'arc/data/0'", "not before the central directory"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, cd1 + 42, 0); }),
                   {"local header of 'arc/data/0'", "names a different entry"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, cd1 + 42, 7); }),
                   {"local header of 'arc/data/0'", "bad signature"});
  expect_zip_error(with([&](std::string& b) { b[cd1 + 46 + 4] = 'X'; }),  // "arc/Xata/0"
                   {"names a different entry"});
  expect_zip_error(with([&](std::string& b) {
                     poke<std::uint32_t>(b, cd1 + 20, 1000);
                     poke<std::uint32_t>(b, cd1 + 24, 1000);
                   }),
                   {"disagrees with the central directory on the CRC or sizes"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, cd1 + 20, 41); }),
                   {"stored entry 'arc/data/0' has 41 stored bytes but a size of 40"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, cd1 + 16, 0xdeadbeefu); }),
                   {"disagrees with the central directory"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, cd1 + 10, 8); }),
                   {"disagrees with the central directory on the compression method"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, cd1 + 28, 0); }), {"has an empty name"});
  expect_zip_error(with([&](std::string& b) { b[cd1 + 46 + 2] = '\0'; }), {"NUL byte"});
  // Data that runs into the central directory (local and central sizes both enlarged).
  expect_zip_error(
      with([&](std::string& b) {
        for (std::uint64_t off : {cd1 + 20, cd1 + 24, L.local_offsets[1] + 18, L.local_offsets[1] + 22})
          poke<std::uint32_t>(b, off, 500);
      }),
      {"data of entry 'arc/data/0'", "runs into the central directory"});
}

TEST_CASE("data descriptors: local CRC and sizes may be zero, never different") {
  ZipSpec s = two_entries();
  for (auto& e : s.entries) e.descriptor = true;
  const auto L = layout_zip(s);
  std::string b = L.bytes();
  poke<std::uint32_t>(b, L.local_offsets[1] + 14,
                      epona::io::crc32({reinterpret_cast<const std::byte*>(b.data()) + L.data_offsets[1], 40}));
  poke<std::uint32_t>(b, L.local_offsets[1] + 22, 40);  // CRC and size filled in, compressed size left 0
  CHECK(open_zip(b).entries().size() == 2);
  poke<std::uint32_t>(b, L.local_offsets[1] + 18, 39);
  expect_zip_error(b,
                   {"local header of 'arc/data/0'", "disagrees with the central directory on the CRC or sizes"});
}

TEST_CASE("duplicate names are refused") {
  ZipSpec s = two_entries();
  s.entries.push_back({"arc/data/0", "again"});
  expect_zip_error(layout_zip(s).bytes(), {"duplicate entry name 'arc/data/0'"});
}

TEST_CASE("ZIP64 corruptions are named") {
  ZipSpec s = two_entries();
  s.zip64 = true;
  const auto L = layout_zip(s);
  const std::string good = L.bytes();
  const auto cd1 = L.central_offsets[1];
  const auto locator = L.zip64_end_offset + 56;
  auto with = [&](auto&& edit) {
    std::string b = good;
    edit(b);
    return b;
  };
  expect_zip_error(with([&](std::string& b) { poke<std::uint64_t>(b, locator + 8, L.zip64_end_offset + 8); }),
                   {"ZIP64 end-record locator points to offset"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint64_t>(b, locator + 8, 0); }), {"no ZIP64 end record"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint64_t>(b, L.zip64_end_offset + 4, 1u << 20); }),
                   {"ZIP64 end record", "invalid size"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint32_t>(b, locator + 16, 2); }), {"multi-disk"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint64_t>(b, L.zip64_end_offset + 48, 1ull << 40); }),
                   {"overlaps the end records"});
  expect_zip_error(with([&](std::string& b) {
                     poke<std::uint16_t>(b, L.eocd_offset + 8, 5);
                     poke<std::uint16_t>(b, L.eocd_offset + 10, 5);
                   }),
                   {"entry count (5) disagrees with the ZIP64 end record (2)"});
  // Central ZIP64 extra: wrong id (missing), too short, and an offset beyond the file.
  const auto extra = cd1 + 46 + std::string("arc/data/0").size();
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, extra, 0x7777); }),
                   {"'arc/data/0'", "no ZIP64 extra field"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, extra + 2, 8); }),
                   {"ZIP64 extra field of entry 'arc/data/0'", "too short"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint16_t>(b, extra + 2, 200); }),
                   {"extra field of entry 'arc/data/0'", "runs past the end"});
  expect_zip_error(with([&](std::string& b) { poke<std::uint64_t>(b, extra + 20, 1ull << 62); }),
                   {"local header of 'arc/data/0'", "not before the central directory"});
  // Local ZIP64 extra disagreeing with the central sizes.
  const auto lextra = L.local_offsets[1] + 30 + std::string("arc/data/0").size();
  expect_zip_error(with([&](std::string& b) { poke<std::uint64_t>(b, lextra + 4, 39); }),
                   {"local header of 'arc/data/0'", "disagrees"});
}

TEST_CASE("the end record is searched for only in the last 64 KiB + 22 bytes") {
  ZipSpec s = two_entries();
  s.comment = std::string(65535, 'c');
  const std::string max_comment = layout_zip(s).bytes();
  CHECK(open_zip(max_comment).entries().size() == 2);
  // Trailing bytes after the end record (the comment length no longer reaches EOF): refused.
  expect_zip_error(layout_zip(two_entries()).bytes() + std::string(70000, '\0'), {"no end-of-central-directory"});
  expect_zip_error(layout_zip(two_entries()).bytes() + "x", {"no end-of-central-directory"});
}

TEST_CASE("every truncation of real and builder archives fails cleanly") {
  for (const std::string& bytes : {read_file(kPklFiles + "bf16_world.pkl"), read_file(kPklFiles + "zip64_full.pkl"),
                                   read_file(kPklFiles + "zip64_local.pkl")}) {
    std::size_t refused = 0;
    for (std::size_t n = 0; n < bytes.size(); ++n) {
      const std::string cut = bytes.substr(0, n);
      try {
        open_zip(cut);
      } catch (const Error& e) {
        ++refused;
        CHECK(std::string(e.what()).find("test.zip") != std::string::npos);
      }
    }
    CHECK(refused == bytes.size());
  }
}

TEST_CASE("single-byte corruption anywhere: an error or a consistent archive, never a crash") {
  for (const char* f : {"bf16_world.pkl", "zip64_full.pkl", "zip64_local.pkl"}) {
    const std::string bytes = read_file(kPklFiles + f);
    std::size_t opened = 0, refused = 0;
    for (std::size_t i = 0; i < bytes.size(); ++i)
      for (unsigned char x : {0x01, 0x80, 0xff}) {
        std::string b = bytes;
        b[i] = char(static_cast<unsigned char>(b[i]) ^ x);
        try {
          const auto zip = open_zip(b);
          for (const auto& e : zip.entries()) {  // everything listed lies inside the file
            CHECK(e.data_offset + e.compressed_size <= b.size());
            if (e.method == 0) CHECK(zip.data(e).data() >= reinterpret_cast<const std::byte*>(b.data()));
          }
          ++opened;
        } catch (const Error&) {
          ++refused;
        }
      }
    CHECK(opened + refused == 3 * bytes.size());
    CHECK(refused > 0);
    MESSAGE(std::string(f), ": ", refused, " corruptions refused, ", opened,
            " harmless (data, timestamps, padding)");
  }
}

TEST_CASE("sparse multi-GB ZIP64 archive: sizes and offsets beyond 4 GiB, zero-copy") {
  const std::uint64_t big = (std::uint64_t{1} << 32) + 4096 + 3;  // > 4 GiB, not aligned
  ZipSpec s;
  s.zip64 = true;
  s.entries.push_back({"arc/data.pkl", "head"});
  ZipSpec::Entry huge{"arc/data/0", "first bytes", big};
  huge.descriptor = true;  // torch.save style
  s.entries.push_back(huge);
  s.entries.push_back({"arc/data/1", "after 4 GiB"});  // its local header offset is > 4 GiB
  const auto L = layout_zip(s);
  const auto path = (std::filesystem::temp_directory_path() / "epona_test_zip_sparse.zip").string();
  try {
    L.write_sparse(path);
  } catch (const Error& e) {
    MESSAGE("skipped: cannot write a sparse file: ", e.what());
    return;
  }
  const auto t0 = std::chrono::steady_clock::now();
  {
    const auto zip = ZipArchive::open(path);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    MESSAGE("opened a ", L.size / 1e9, " GB archive in ", ms, " ms");
    CHECK(ms < 1000);
    const auto& e0 = zip.at("arc/data/0");
    CHECK(e0.size == big);
    const auto d0 = zip.data(e0);
    CHECK(d0.size() == big);
    CHECK(as_string(d0.subspan(0, 11)) == "first bytes");
    CHECK(d0[big - 1] == std::byte{0});
    const auto& e1 = zip.at("arc/data/1");
    CHECK(e1.header_offset > 0xffffffffull);
    CHECK(as_string(zip.data(e1)) == "after 4 GiB");
    CHECK_NOTHROW(zip.verify_crc(e1));
  }
  std::filesystem::remove(path);
}
