// Issue #36, linear readers: the safetensors header parse and the pickle reader do work linear in
// their input. Checked by counting operations (io::JsonWork, pickle::Work), never by timing: a
// header of 80k tensors took 237 s with nlohmann's callback parser (it rescans the enclosing
// object after every closed one), a 2 MB pickle repeating one long dict key took minutes and GBs.
#include <doctest/doctest.h>

#include <cstdint>
#include <cstring>
#include <string>

#include "epona/io/pickle.hpp"
#include "epona/io/safetensors.hpp"

using namespace epona;

namespace {

// A safetensors image of n one-element F32 tensors.
std::string safetensors_of(int n) {
  std::string header = "{";
  for (int i = 0; i < n; ++i) {
    if (i) header += ',';
    header += "\"layer." + std::to_string(i) + ".weight\":{\"dtype\":\"F32\",\"shape\":[1],\"data_offsets\":[" +
              std::to_string(4 * i) + "," + std::to_string(4 * i + 4) + "]}";
  }
  header += "}";
  std::string file(8, '\0');
  const std::uint64_t len = header.size();
  for (int k = 0; k < 8; ++k) file[k] = static_cast<char>((len >> (8 * k)) & 0xff);
  return file + header + std::string(4 * std::size_t(n), '\0');
}

std::uint64_t header_events(int n) {
  const std::string file = safetensors_of(n);
  io::JsonWork work;
  const std::string_view header(file.data() + 8, file.size() - 8 - 4 * std::size_t(n));
  const auto j = io::safetensors_detail::parse_header(header, "t.safetensors", &work);
  CHECK(j.size() == std::size_t(n));
  return work.events;
}

std::string u32le(std::uint32_t v) {
  std::string s(4, '\0');
  for (int k = 0; k < 4; ++k) s[k] = static_cast<char>((v >> (8 * k)) & 0xff);
  return s;
}

}  // namespace

TEST_CASE("safetensors header: work per tensor is constant (events counted, 2k vs 32k tensors)") {
  const std::uint64_t small = header_events(2000), large = header_events(32000);
  MESSAGE("parse events: 2000 tensors ", small, ", 32000 tensors ", large);
  // Each entry is a fixed number of SAX events (key, object, 3 keys, 3 values, 2 lists...).
  CHECK(large - 2 == 16 * (small - 2));  // the top object's open and close, then per-tensor work
  CHECK(small <= 20 * 2000);
}

TEST_CASE("safetensors: a file of 32k tensors parses completely") {
  const std::string file = safetensors_of(32000);
  const std::span<const std::byte> bytes(reinterpret_cast<const std::byte*>(file.data()), file.size());
  const auto st = io::parse_safetensors(bytes, "t.safetensors", nullptr);
  CHECK(st.tensors.size() == 32000);
}

TEST_CASE("pickle: a long key set again and again costs its length once, not once per SETITEM") {
  const std::size_t key_bytes = 1 << 20, repeats = 100'000;
  std::string p = "\x80\x02}";  // PROTO 2, EMPTY_DICT
  p += "X" + u32le(key_bytes) + std::string(key_bytes, 'k') + std::string("q\x00", 2) + "K\x01s";  // d[key] = 1, key memo 0
  for (std::size_t i = 0; i < repeats; ++i) p += std::string("h\x00K\x02s", 5);  // d[memo 0] = 2
  for (std::size_t i = 0; i < repeats; ++i) p += std::string("}h\x00K\x03s", 6);  // a new dict {memo 0: 3}
  p += ".";
  const auto doc = io::pickle::unpickle({reinterpret_cast<const std::byte*>(p.data()), p.size()}, "keys.pkl");
  MESSAGE("pickle of ", p.size(), " bytes: ", doc.work().text_bytes, " bytes of text hashed");
  CHECK(doc.work().text_bytes <= p.size());  // each input byte hashed at most once
  const auto& last = doc.dict(doc.root);
  REQUIRE(last.items.size() == 1);
  CHECK(doc.str(last.items[0].first).size() == key_bytes);
}

TEST_CASE("pickle: equal key texts from different strings are one key, as in Python") {
  std::string p = "\x80\x02}";
  p += std::string("X") + u32le(3) + "abc" + "K\x01s";
  p += std::string("X") + u32le(3) + "abc" + "K\x02s";
  p += std::string("X") + u32le(3) + "abd" + "K\x03s";
  p += ".";
  const auto doc = io::pickle::unpickle({reinterpret_cast<const std::byte*>(p.data()), p.size()}, "eq.pkl");
  const auto& d = doc.dict(doc.root);
  REQUIRE(d.items.size() == 2);
  CHECK(d.items[0].second.i == 2);
  REQUIRE(doc.find(d, "abd") != nullptr);
  CHECK(doc.find(d, "abd")->i == 3);
  CHECK(doc.find(d, "abe") == nullptr);
}
