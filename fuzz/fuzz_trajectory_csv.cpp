// fuzz/fuzz_trajectory_csv.cpp — parse_trajectory_csv (header, step/waypoint grid order and
// completeness, values) on arbitrary text; an accepted trajectory must round-trip bit-exactly
// through trajectory_to_csv.
#include <cstring>

#include "epona/domain/trajectory_io.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(trajectory_csv) {
  return epona_fuzz::run([&] {
    const auto t = epona::io::parse_trajectory_csv(epona_fuzz::as_text(data, size), "fuzz.csv");
    const auto again = epona::io::parse_trajectory_csv(epona::io::trajectory_to_csv(t), "round trip");
    epona_fuzz::require(again.shape() == t.shape() && std::memcmp(again.data(), t.data(), t.nbytes()) == 0,
                        "trajectory_to_csv -> parse_trajectory_csv keeps every bit");
  });
}
