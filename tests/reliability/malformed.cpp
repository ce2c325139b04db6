// Issue #36, silent success on malformed input: ZIP entries that overlap in the file are refused
// (one stretch of bytes read under two names, an entry hidden in another's data).
#include <doctest/doctest.h>

#include <string>

#include "../io/zip_builder.hpp"
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
