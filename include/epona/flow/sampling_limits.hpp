// epona/flow/sampling_limits.hpp — the constants of the rectified-flow schedule that the official
// code hard-codes (the shift of get_schedule) and the bound on sampling steps, with the check
// that enforces it. Below the model so that flow/schedule.hpp needs nothing of model/config.hpp,
// which includes this header (constants:: names them as before).
#pragma once

#include <cstdint>

#include "epona/core/error.hpp"

namespace epona {

namespace constants {
// Sampling schedule shift (get_schedule): mu is linear through (x1, base) and (x2, max).
inline constexpr double schedule_base_shift = 0.5;
inline constexpr double schedule_max_shift = 1.15;
inline constexpr double schedule_x1 = 256.0;
inline constexpr double schedule_x2 = 4096.0;
// Most sampling steps accepted (the official runs use 100); a larger count is a typo or an
// attack, refused before the schedule or any output is allocated.
inline constexpr std::int64_t max_sampling_steps = 100000;
}  // namespace constants

// Throws (naming `what`) unless 1 <= steps <= constants::max_sampling_steps.
inline void check_sampling_steps(std::int64_t steps, const char* what = "sampling steps") {
  EPONA_CHECK(steps >= 1 && steps <= constants::max_sampling_steps, what, " must be in [1, ",
              constants::max_sampling_steps, "], got ", steps);
}

}  // namespace epona
