// epona/flow/schedule.hpp — the rectified-flow time grid of Epona's samplers
// (models/modules/sampling.py `get_schedule` with the shift on): num_steps+1 values from 0
// (noise) to 1 (data), bit-identical to the official float32 tensor arithmetic.
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/flow/sampling_limits.hpp"

namespace epona::flow {

struct ScheduleShift {
  double base_shift = constants::schedule_base_shift;
  double max_shift = constants::schedule_max_shift;
  double x1 = constants::schedule_x1;
  double x2 = constants::schedule_x2;

  // mu(L): the line through (x1, base_shift) and (x2, max_shift), in Python double.
  double mu(std::int64_t seq_len) const {
    const double m = (max_shift - base_shift) / (x2 - x1);
    const double b = base_shift - m * x1;
    return m * static_cast<double>(seq_len) + b;
  }
};

// The official computation step by step:
//   s = torch.linspace(1, 0, N+1)            (fp32; first half start + step·i as one FMA,
//                                             second half end - step·(N-i))
//   sigma = e^mu * reciprocal(e^mu + (reciprocal(s) - 1))   (Python `a / tensor` is
//                                             `tensor.reciprocal() * a`; e^mu rounded to fp32)
//   t = 1 - sigma
// s = 0 gives 1/0 = inf and sigma = 0, hence t_N = 1.
inline std::vector<float> get_schedule(std::int64_t num_steps, std::int64_t seq_len, const ScheduleShift& shift = {}) {
  check_sampling_steps(num_steps);
  EPONA_CHECK(seq_len >= 1, "schedule sequence length must be at least 1, got ", seq_len);
  const float e_mu = static_cast<float>(std::exp(shift.mu(seq_len)));
  const std::int64_t points = num_steps + 1, halfway = points / 2;
  const float step = (0.0f - 1.0f) / static_cast<float>(num_steps);
  std::vector<float> t(static_cast<std::size_t>(points));
  for (std::int64_t i = 0; i < points; ++i) {
    const float s = i < halfway ? std::fma(step, static_cast<float>(i), 1.0f)
                                : 0.0f - step * static_cast<float>(num_steps - i);
    const float inv_s = 1.0f / s;
    const float denom = e_mu + (inv_s - 1.0f);
    volatile float sigma = (1.0f / denom) * e_mu;  // volatile: no FMA contraction into 1 - sigma
    t[static_cast<std::size_t>(i)] = 1.0f - sigma;
  }
  return t;
}

}  // namespace epona::flow
