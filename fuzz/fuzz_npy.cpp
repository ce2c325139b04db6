// fuzz/fuzz_npy.cpp — the .npy reader (magic, version, header length, the header literal parser,
// dtype, shape overflow, data size) on arbitrary bytes, read as float and as double; an accepted
// file must round-trip bit-exactly through to_npy_bytes.
#include <cstring>

#include "epona/io/npy.hpp"
#include "fuzz_common.hpp"

namespace npy_target {
template <class T>
void read_and_round_trip(std::span<const std::byte> bytes) {
  const auto a = epona::io::parse_npy<T>(bytes, "fuzz.npy");
  const std::string again = epona::io::to_npy_bytes(a.values);
  const auto b = epona::io::parse_npy<T>({reinterpret_cast<const std::byte*>(again.data()), again.size()}, "round trip");
  epona_fuzz::require(b.values.shape() == a.values.shape(), "round trip keeps the shape");
  epona_fuzz::require(std::memcmp(a.values.data(), b.values.data(), a.values.nbytes()) == 0,
                      "round trip keeps every bit");
}
}  // namespace npy_target

EPONA_FUZZ_TARGET(npy) {
  using namespace npy_target;
  const auto bytes = epona_fuzz::as_bytes(data, size);
  epona_fuzz::run([&] { read_and_round_trip<float>(bytes); });
  return epona_fuzz::run([&] { read_and_round_trip<double>(bytes); });
}
