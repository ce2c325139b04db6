// epona/nn/embeddings.hpp — the two sinusoidal embeddings, on the host, in the official fp32
// operation order: the Fourier embedding of pose/yaw coordinates
// (utils/embeddings.py `get_fourier_embeds_from_coordinates`: [sin | cos], frequencies
// max_period^(k/half)) and the DiT timestep embedding (dit_modules/layers.py
// `timestep_embedding`: t·factor, [cos | sin], frequencies exp(-ln(max_period)·k/half)).
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include "epona/core/error.hpp"

namespace epona::nn {

// out[i, :] (dim floats) = [sin(c_i·f_0..f_{h-1}), cos(c_i·f_0..f_{h-1})], h = dim/2,
// f_k = max_period^(k/h) (fp32 power), products and sin/cos in fp32.
inline void fourier_embed(const float* coords, std::int64_t n, std::int64_t dim, float max_period, float* out) {
  EPONA_CHECK(dim > 0 && dim % 2 == 0, "Fourier embedding width ", dim, " is not positive and even");
  const std::int64_t half = dim / 2;
  std::vector<float> freq(static_cast<std::size_t>(half));
  for (std::int64_t k = 0; k < half; ++k)
    freq[k] = std::pow(max_period, static_cast<float>(k) / static_cast<float>(half));
  for (std::int64_t i = 0; i < n; ++i) {
    float* row = out + i * dim;
    for (std::int64_t k = 0; k < half; ++k) {
      const float arg = coords[i] * freq[k];
      row[k] = std::sin(arg);
      row[half + k] = std::cos(arg);
    }
  }
}

// out[i, :] (dim floats) = [cos(a_0..a_{h-1}), sin(a_0..a_{h-1})] (+ a zero column if dim is
// odd), a_k = (factor·t_i)·g_k, g_k = exp((fp32(-ln max_period)·k)/h) — every step fp32.
inline void timestep_embedding(const float* t, std::int64_t n, std::int64_t dim, double max_period,
                               float time_factor, float* out) {
  EPONA_CHECK(dim >= 2, "timestep embedding width ", dim, " is smaller than 2");
  const std::int64_t half = dim / 2;
  const float neg_log_period = static_cast<float>(-std::log(max_period));
  std::vector<float> freq(static_cast<std::size_t>(half));
  for (std::int64_t k = 0; k < half; ++k)
    freq[k] = std::exp((neg_log_period * static_cast<float>(k)) / static_cast<float>(half));
  for (std::int64_t i = 0; i < n; ++i) {
    const float scaled = time_factor * t[i];
    float* row = out + i * dim;
    for (std::int64_t k = 0; k < half; ++k) {
      const float arg = scaled * freq[k];
      row[k] = std::cos(arg);
      row[half + k] = std::sin(arg);
    }
    if (dim % 2) row[dim - 1] = 0.0f;
  }
}

}  // namespace epona::nn
