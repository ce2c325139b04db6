// epona/nn/pixel_shuffle.hpp — F.pixel_unshuffle / F.pixel_shuffle and the DC-AE's two
// parameter-free shortcuts on feature maps: PixelUnshuffleChannelAveragingDownSampleLayer
// (unshuffle, then mean of consecutive channel groups) and ChannelDuplicatingPixelUnshuffleUpSampleLayer
// (repeat-interleave channels, then shuffle). The `add_` forms accumulate into a residual sum;
// pixel_shuffle_add_duplicate is the upsampling pair in one call.
#pragma once

#include <cstdint>

#include "epona/core/tensor.hpp"
#include "epona/cpu/pixel_shuffle.hpp"
#include "epona/nn/feature_map.hpp"

namespace epona::nn {

namespace shuffle_detail {
template <class A, class B>
ShuffleShape geometry(const Tensor<A, B>& x, std::int64_t factor, const char* what) {
  const MapDims d = map_dims(x, what);
  return {d.batch, d.channels, d.height, d.width, factor};
}
}  // namespace shuffle_detail

// y (+)= A(x; C_out, r): C channels at H x W -> C_out = y's channels at H/r x W/r.
template <class Ctx, class A, class B>
void add_channel_average_down(Ctx& ctx, const Tensor<A, B>& x, Tensor<A, B>& y, std::int64_t factor,
                              bool accumulate = true) {
  const auto s = shuffle_detail::geometry(x, factor, "channel averaging shortcut");
  const MapDims o = map_dims(y, "channel averaging shortcut output");
  EPONA_CHECK(o.batch == s.batch && o.height * factor == s.height && o.width * factor == s.width,
              "channel averaging shortcut: output ", shape_str(y.shape()), " does not fit input ",
              shape_str(x.shape()), " at factor ", factor);
  pixel_unshuffle_average(ctx, x.data(), y.data(), s, o.channels, accumulate);
}

// y (+)= D(x; C_out, r): C channels at H x W -> C_out = y's channels at H·r x W·r.
template <class Ctx, class A, class B>
void add_channel_duplicate_up(Ctx& ctx, const Tensor<A, B>& x, Tensor<A, B>& y, std::int64_t factor,
                              bool accumulate = true) {
  const auto s = shuffle_detail::geometry(x, factor, "channel duplicating shortcut");
  const MapDims o = map_dims(y, "channel duplicating shortcut output");
  EPONA_CHECK(o.batch == s.batch && o.height == s.height * factor && o.width == s.width * factor,
              "channel duplicating shortcut: output ", shape_str(y.shape()), " does not fit input ",
              shape_str(x.shape()), " at factor ", factor);
  pixel_shuffle_duplicate(ctx, x.data(), y.data(), s, o.channels, accumulate);
}

template <class Ctx, class A, class B>
Tensor<A, B> channel_average_down(Ctx& ctx, const Tensor<A, B>& x, std::int64_t channels_out, std::int64_t factor) {
  const auto s = shuffle_detail::geometry(x, factor, "channel averaging shortcut");
  EPONA_CHECK(factor >= 1 && s.height % factor == 0 && s.width % factor == 0, "channel averaging shortcut: ",
              shape_str(x.shape()), " is not divisible by factor ", factor);
  Tensor<A, B> y = new_map<A, B>(ctx, {s.batch, channels_out, s.height / factor, s.width / factor});
  add_channel_average_down(ctx, x, y, factor, false);
  return y;
}

template <class Ctx, class A, class B>
Tensor<A, B> channel_duplicate_up(Ctx& ctx, const Tensor<A, B>& x, std::int64_t channels_out, std::int64_t factor) {
  const auto s = shuffle_detail::geometry(x, factor, "channel duplicating shortcut");
  Tensor<A, B> y = new_map<A, B>(ctx, {s.batch, channels_out, s.height * factor, s.width * factor});
  add_channel_duplicate_up(ctx, x, y, factor, false);
  return y;
}

// F.pixel_unshuffle(x, r): C channels at H x W -> C·r² channels at H/r x W/r.
template <class Ctx, class A, class B>
Tensor<A, B> pixel_unshuffle(Ctx& ctx, const Tensor<A, B>& x, std::int64_t factor) {
  const auto s = shuffle_detail::geometry(x, factor, "pixel_unshuffle");
  return channel_average_down(ctx, x, s.channels * factor * factor, factor);
}

// F.pixel_shuffle(x, r): C·r² channels at H x W -> C channels at H·r x W·r.
template <class Ctx, class A, class B>
Tensor<A, B> pixel_shuffle(Ctx& ctx, const Tensor<A, B>& x, std::int64_t factor) {
  const auto s = shuffle_detail::geometry(x, factor, "pixel_shuffle");
  EPONA_CHECK(factor >= 1 && s.channels % (factor * factor) == 0, "pixel_shuffle: ", s.channels,
              " channels are not divisible by factor² = ", factor * factor);
  return channel_duplicate_up(ctx, x, s.channels / (factor * factor), factor);
}

// The upsampling pair F.pixel_shuffle(main, r) + D(x; C_out, r), C_out = main's channels / r²:
// one pass where the backend fuses it (CUDA: pixel_shuffle_add_duplicate_fused), else the shuffle and
// the accumulating shortcut. Same result either way (the sum is rounded once).
template <class Ctx, class A, class B>
Tensor<A, B> pixel_shuffle_add_duplicate(Ctx& ctx, const Tensor<A, B>& main, const Tensor<A, B>& x,
                                         std::int64_t factor) {
  const auto s = shuffle_detail::geometry(main, factor, "pixel_shuffle");
  const MapDims dx = map_dims(x, "channel duplicating shortcut");
  EPONA_CHECK(factor >= 1 && s.channels % (factor * factor) == 0, "pixel_shuffle: ", s.channels,
              " channels are not divisible by factor² = ", factor * factor);
  EPONA_CHECK(dx.batch == s.batch && dx.height == s.height && dx.width == s.width, "upsampling pair: shortcut input ",
              shape_str(x.shape()), " does not fit the convolution's output ", shape_str(main.shape()));
  const std::int64_t out_channels = s.channels / (factor * factor);
  if constexpr (!is_host_backend<B>) {
    Tensor<A, B> y = new_map<A, B>(ctx, {s.batch, out_channels, s.height * factor, s.width * factor});
    if (pixel_shuffle_add_duplicate_fused(ctx, main.data(), x.data(), y.data(), s, out_channels, dx.channels)) return y;
  }
  Tensor<A, B> y = pixel_shuffle(ctx, main, factor);
  add_channel_duplicate_up(ctx, x, y, factor);
  return y;
}

// F.pixel_shuffle(x, r) as the public NCHW float32 tensor `out` (N, C/r², H·r, W·r): the
// decoder's last step. One pass on channels-last backends that fuse it, else shuffle + map_to_nchw.
template <class Ctx, class A, class B>
void pixel_shuffle_to_nchw(Ctx& ctx, const Tensor<A, B>& x, std::int64_t factor, Tensor<float, B>& out) {
  const auto s = shuffle_detail::geometry(x, factor, "pixel_shuffle");
  EPONA_CHECK(factor >= 1 && s.channels % (factor * factor) == 0, "pixel_shuffle: ", s.channels,
              " channels are not divisible by factor² = ", factor * factor);
  const std::int64_t C = s.channels / (factor * factor);
  check_shape(out, {s.batch, C, s.height * factor, s.width * factor}, "pixel_shuffle_to_nchw output");
  if constexpr (channels_last_maps<B>) {
    if (pixel_shuffle_to_nchw_fused(ctx, x.data(), out.data(), s.batch, C, s.height, s.width, factor)) return;
  }
  map_to_nchw(ctx, pixel_shuffle(ctx, x, factor), out);
}

}  // namespace epona::nn
