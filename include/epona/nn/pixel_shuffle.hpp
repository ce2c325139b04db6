// epona/nn/pixel_shuffle.hpp — F.pixel_unshuffle / F.pixel_shuffle and the DC-AE's two
// parameter-free shortcuts on tensors: PixelUnshuffleChannelAveragingDownSampleLayer (unshuffle,
// then mean of consecutive channel groups) and ChannelDuplicatingPixelUnshuffleUpSampleLayer
// (repeat-interleave channels, then shuffle). The `add_` forms accumulate into a residual sum.
#pragma once

#include <cstdint>

#include "epona/core/tensor.hpp"
#include "epona/cpu/pixel_shuffle.hpp"

namespace epona::nn {

namespace shuffle_detail {
template <class B>
ShuffleShape geometry(const Tensor<float, B>& x, std::int64_t factor, const char* what) {
  EPONA_CHECK(x.dim() == 4, what, ": input must be (N, C, H, W), got ", shape_str(x.shape()));
  return {x.size(0), x.size(1), x.size(2), x.size(3), factor};
}
}  // namespace shuffle_detail

// y (+)= A(x; C_out, r): (N, C, H, W) -> (N, C_out, H/r, W/r), C_out = y's channels.
template <class Ctx, class B>
void add_channel_average_down(Ctx& ctx, const Tensor<float, B>& x, Tensor<float, B>& y, std::int64_t factor,
                              bool accumulate = true) {
  const auto s = shuffle_detail::geometry(x, factor, "channel averaging shortcut");
  EPONA_CHECK(y.dim() == 4 && y.size(0) == s.batch && y.size(2) * factor == s.height &&
                  y.size(3) * factor == s.width,
              "channel averaging shortcut: output ", shape_str(y.shape()), " does not fit input ",
              shape_str(x.shape()), " at factor ", factor);
  pixel_unshuffle_average(ctx, x.data(), y.data(), s, y.size(1), accumulate);
}

// y (+)= D(x; C_out, r): (N, C, H, W) -> (N, C_out, H·r, W·r), C_out = y's channels.
template <class Ctx, class B>
void add_channel_duplicate_up(Ctx& ctx, const Tensor<float, B>& x, Tensor<float, B>& y, std::int64_t factor,
                              bool accumulate = true) {
  const auto s = shuffle_detail::geometry(x, factor, "channel duplicating shortcut");
  EPONA_CHECK(y.dim() == 4 && y.size(0) == s.batch && y.size(2) == s.height * factor &&
                  y.size(3) == s.width * factor,
              "channel duplicating shortcut: output ", shape_str(y.shape()), " does not fit input ",
              shape_str(x.shape()), " at factor ", factor);
  pixel_shuffle_duplicate(ctx, x.data(), y.data(), s, y.size(1), accumulate);
}

template <class Ctx, class B>
Tensor<float, B> channel_average_down(Ctx& ctx, const Tensor<float, B>& x, std::int64_t channels_out,
                                      std::int64_t factor) {
  shuffle_detail::geometry(x, factor, "channel averaging shortcut");
  EPONA_CHECK(x.size(2) % factor == 0 && x.size(3) % factor == 0, "channel averaging shortcut: ",
              shape_str(x.shape()), " is not divisible by factor ", factor);
  Tensor<float, B> y({x.size(0), channels_out, x.size(2) / factor, x.size(3) / factor});
  add_channel_average_down(ctx, x, y, factor, false);
  return y;
}

template <class Ctx, class B>
Tensor<float, B> channel_duplicate_up(Ctx& ctx, const Tensor<float, B>& x, std::int64_t channels_out,
                                      std::int64_t factor) {
  shuffle_detail::geometry(x, factor, "channel duplicating shortcut");
  Tensor<float, B> y({x.size(0), channels_out, x.size(2) * factor, x.size(3) * factor});
  add_channel_duplicate_up(ctx, x, y, factor, false);
  return y;
}

// F.pixel_unshuffle(x, r): (N, C, H, W) -> (N, C·r², H/r, W/r).
template <class Ctx, class B>
Tensor<float, B> pixel_unshuffle(Ctx& ctx, const Tensor<float, B>& x, std::int64_t factor) {
  shuffle_detail::geometry(x, factor, "pixel_unshuffle");
  return channel_average_down(ctx, x, x.size(1) * factor * factor, factor);
}

// F.pixel_shuffle(x, r): (N, C·r², H, W) -> (N, C, H·r, W·r).
template <class Ctx, class B>
Tensor<float, B> pixel_shuffle(Ctx& ctx, const Tensor<float, B>& x, std::int64_t factor) {
  shuffle_detail::geometry(x, factor, "pixel_shuffle");
  EPONA_CHECK(factor >= 1 && x.size(1) % (factor * factor) == 0, "pixel_shuffle: ", x.size(1),
              " channels are not divisible by factor² = ", factor * factor);
  return channel_duplicate_up(ctx, x, x.size(1) / (factor * factor), factor);
}

}  // namespace epona::nn
