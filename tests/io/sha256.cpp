// Tests for epona/io/sha256.hpp: the standard vectors of FIPS 180-4 (as listed by NIST's
// examples), one million 'a' fed in odd-sized chunks so that block boundaries fall inside
// chunks, and a file hashed by streaming it equal to the in-memory hash.
#include <doctest/doctest.h>

#include <cstddef>
#include <fstream>
#include <string>
#include <vector>

#include "epona/io/sha256.hpp"
#include "../temp_dir.hpp"
#include "../bytes.hpp"

using namespace epona;
using epona::test::as_bytes;

namespace {

std::string digest_of(const std::string& text) {
  io::Sha256 h;
  h.update(text);
  return io::hex(h.finish());
}

}  // namespace

TEST_CASE("sha256: the standard vectors") {
  CHECK(digest_of("") == "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  CHECK(digest_of("abc") == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  CHECK(digest_of("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq") ==
        "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
  CHECK(digest_of("abcdefghbcdefghicdefghijdefghijkefghijklfghijklmghijklmnhijklmnoijklmnopjklmnopqklmnopqrlmnopqrsmnopqrst"
                  "nopqrstu") == "cf5b16a778af8380036ce59e7b0492370b249b11e8f07a51afac45037afee9d1");
}

TEST_CASE("sha256: one million 'a' in odd-sized chunks") {
  const std::string million(1'000'000, 'a');
  const std::string expected = "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0";
  CHECK(io::hex(io::sha256(as_bytes(million))) == expected);
  for (const std::size_t chunk : {std::size_t{1}, std::size_t{7}, std::size_t{63}, std::size_t{65}, std::size_t{1000003}}) {
    io::Sha256 h;
    for (std::size_t at = 0; at < million.size(); at += chunk)
      h.update(std::string_view(million).substr(at, chunk));
    CHECK_MESSAGE(io::hex(h.finish()) == expected, "chunk of ", chunk, " bytes");
  }
}

TEST_CASE("sha256: lengths around the padding boundary (55, 56, 63, 64, 65 bytes)") {
  // The length field fits after the 0x80 byte only up to 55 bytes; past that the padding spills
  // into a second block. Fed whole and byte by byte, each length must hash the same.
  for (const std::size_t n : {55, 56, 63, 64, 65, 119, 120}) {
    const std::string text(n, 'x');
    io::Sha256 bytewise;
    for (const char c : text) bytewise.update(std::string_view(&c, 1));
    CHECK_MESSAGE(io::hex(bytewise.finish()) == digest_of(text), n, " bytes");
  }
  CHECK(digest_of(std::string(64, 'a')) == "ffe054fe7ae0cb6dc65c3af9b61d5209f439851db43d0ba5997337df154668eb");
}

TEST_CASE("sha256_file: streamed in blocks, equal to the in-memory hash; progress reaches the size") {
  test::TempDir dir("epona_sha256");
  std::string data(300'001, '\0');
  for (std::size_t i = 0; i < data.size(); ++i) data[i] = static_cast<char>((i * 2654435761u) >> 13);
  const std::string path = dir / "blob.bin";
  std::ofstream(path, std::ios::binary).write(data.data(), static_cast<std::streamsize>(data.size()));
  std::uint64_t last = 0, calls = 0;
  const auto d = io::sha256_file(path, [&](std::uint64_t done, std::uint64_t total) {
    CHECK(total == data.size());
    CHECK(done > last);
    last = done, ++calls;
  }, 4099);
  CHECK(io::hex(d) == io::hex(io::sha256(as_bytes(data))));
  CHECK(last == data.size());
  CHECK(calls == (data.size() + 4098) / 4099);
  CHECK(io::hex(io::sha256_file(path)) == io::hex(io::sha256(as_bytes(data))));
}

TEST_CASE("sha256_file: an empty file, a missing file, a folder") {
  test::TempDir dir("epona_sha256");
  std::ofstream(dir / "empty").flush();
  CHECK(io::hex(io::sha256_file(dir / "empty")) == "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  CHECK_THROWS_WITH_AS(io::sha256_file(dir / "absent"), doctest::Contains("file does not exist"), Error);
  CHECK_THROWS_WITH_AS(io::sha256_file(dir.path.string()), doctest::Contains("is a directory"), Error);
}
