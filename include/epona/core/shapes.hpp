// epona/core/shapes.hpp — the descriptors the convolutional autoencoder's (DC-AE's) kernels take,
// defined once below the backends so that epona::cpu and epona::cuda kernels take the same types
// and cuda/ needs nothing from cpu/ (Eigen, xsimd) for them: the fused activation, the
// convolution and (un)shuffle geometries, and the order of LiteMLA's linear attention.
#pragma once

#include <cstdint>

#include "epona/core/error.hpp"

namespace epona {

// Activation fused after a convolution or norm (the DC-AE uses ReLU and SiLU only).
enum class ConvAct { None, Relu, Silu };

// Geometry of a stride-1 convolution with zero padding kernel/2 on every side.
// Weight layout [out, in/groups, kernel, kernel] (PyTorch), bias [out] or null.
struct Conv2dShape {
  std::int64_t batch = 1, in_channels = 0, height = 0, width = 0;
  std::int64_t out_channels = 0, kernel = 1, groups = 1;
};

inline void check_conv2d_shape(const Conv2dShape& s) {
  EPONA_CHECK(s.batch >= 0 && s.in_channels > 0 && s.out_channels > 0 && s.height > 0 && s.width > 0,
              "conv2d: bad geometry N=", s.batch, " C=", s.in_channels, " H=", s.height, " W=", s.width,
              " O=", s.out_channels);
  EPONA_CHECK(s.kernel >= 1 && s.kernel % 2 == 1, "conv2d: kernel size must be odd (same padding), got ",
              s.kernel);
  EPONA_CHECK(s.groups >= 1 && s.in_channels % s.groups == 0 && s.out_channels % s.groups == 0,
              "conv2d: groups=", s.groups, " must divide in_channels=", s.in_channels, " and out_channels=",
              s.out_channels);
}

// Geometry of a (un)shuffle: input (batch, channels, height, width), factor r.
struct ShuffleShape {
  std::int64_t batch = 1, channels = 0, height = 0, width = 0, factor = 1;
};

// Evaluation order of LiteMLA's linear attention: Auto is the reference's choice (Linear when
// H·W > d, else Quadratic); the others force one order (tests compare the two).
enum class AttentionOrder { Auto, Linear, Quadratic };

}  // namespace epona
