// fuzz/fuzz_trajectory_json.cpp — parse_trajectory_json ("steps" grid, "format", "units", values)
// on arbitrary text; an accepted trajectory must round-trip bit-exactly through trajectory_to_json.
#include <cstring>

#include "epona/domain/trajectory_io.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(trajectory_json) {
  return epona_fuzz::run([&] {
    const auto t = epona::io::parse_trajectory_json(epona_fuzz::as_text(data, size), "fuzz.json");
    const auto again = epona::io::parse_trajectory_json(epona::io::trajectory_to_json(t), "round trip");
    epona_fuzz::require(again.shape() == t.shape() && std::memcmp(again.data(), t.data(), t.nbytes()) == 0,
                        "trajectory_to_json -> parse_trajectory_json keeps every bit");
  });
}
