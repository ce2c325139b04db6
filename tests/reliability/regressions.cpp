// One test per bug the fuzzers found (docs/reliability.md lists them): the behaviour the fixed
// code must have on the input class that triggered it. The triggering inputs themselves are
// replayed by fuzz_replay.cpp from fuzz/regressions/<target>/.
#include <doctest/doctest.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>

#include "epona/io/pickle.hpp"

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
