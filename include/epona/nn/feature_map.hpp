// epona/nn/feature_map.hpp — how the DC-AE's feature maps live on a backend: their memory order
// (NCHW on the CPU, channels-last NHWC on CUDA, where convolutions are implicit GEMMs over
// pixels), their element type (float on the CPU; the weight type on CUDA, so bf16 runs on tensor
// cores), and the helpers layer code uses to stay backend-generic (allocation, copies, layouts).
#pragma once

#include <cstdint>
#include <string>
#include <type_traits>
#include <utility>

#include "epona/core/backend.hpp"
#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cpu/copy_fill_axpy.hpp"
#include "epona/cpu/pixel_shuffle.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona {

// Feature maps of backend B are stored channels-last, (N, H, W, C), instead of (N, C, H, W).
// Conv weights then follow as [out, k, k, in/groups]. The public DC-AE API stays NCHW float.
// (CUDA: convolutions are implicit GEMMs over pixels, which want channels contiguous.)
template <class B> inline constexpr bool channels_last_maps = false;
template <> inline constexpr bool channels_last_maps<Cuda> = true;

// Element type of the DC-AE's activations for weights of type T on backend B (the backend's
// Activation<B, T>): float32 on the CPU (bf16 weights are widened per call); the weight type on
// CUDA, so bf16 convolutions run on tensor cores.
template <class B, class T> using activation_t = Activation<B, T>;

namespace nn {

// Logical extents of a feature map, whatever its memory order.
struct MapDims {
  std::int64_t batch = 0, channels = 0, height = 0, width = 0;
  std::int64_t pixels() const { return height * width; }
  std::int64_t numel() const { return batch * channels * height * width; }
  bool operator==(const MapDims&) const = default;
};

template <class B>
Shape map_shape(const MapDims& d) {
  if constexpr (channels_last_maps<B>) return {d.batch, d.height, d.width, d.channels};
  return {d.batch, d.channels, d.height, d.width};
}

// "(N, C, H, W)" or "(N, H, W, C)" with C spelled out, for error messages.
template <class B>
std::string map_layout_str(std::int64_t channels) {
  const std::string c = channels > 0 ? std::to_string(channels) : std::string("C");
  return channels_last_maps<B> ? "(N, H, W, " + c + ")" : "(N, " + c + ", H, W)";
}

// Extents of x read in B's memory order; `channels` > 0 also checks them. Errors name `what`.
template <class A, class B>
MapDims map_dims(const Tensor<A, B>& x, const std::string& what, std::int64_t channels = 0) {
  const bool ok = x.dim() == 4 && (channels <= 0 || x.size(channels_last_maps<B> ? 3 : 1) == channels);
  EPONA_CHECK(ok, what, ": input must be ", map_layout_str<B>(channels), ", got ", shape_str(x.shape()));
  if constexpr (channels_last_maps<B>) return {x.size(0), x.size(3), x.size(1), x.size(2)};
  return {x.size(0), x.size(1), x.size(2), x.size(3)};
}

// The four arguments that address channels [first, first + count) of every pixel of a map as
// `rows` rows of `width` consecutive elements `stride` apart, starting `offset` elements in:
// one row per image in NCHW (a block of planes), one per pixel channels-last.
struct ChannelBlock {
  std::int64_t offset = 0, rows = 0, width = 0, stride = 0;
};
template <class B>
ChannelBlock channel_block(const MapDims& d, std::int64_t first, std::int64_t count) {
  if constexpr (channels_last_maps<B>) return {first, d.batch * d.pixels(), count, d.channels};
  return {first * d.pixels(), d.batch, count * d.pixels(), d.channels * d.pixels()};
}

// A tensor for intermediate results. The CPU allocates; CUDA takes it from the stream-ordered
// pool of the context's stream (`scratch_tensor`, found by argument-dependent lookup), so the
// many short-lived maps of a forward pass cost no cudaMalloc/cudaFree.
template <class A, class B, class Ctx>
Tensor<A, B> new_tensor(Ctx& ctx, Shape shape) {
  if constexpr (is_host_backend<B>) {
    (void)ctx;
    return Tensor<A, B>(std::move(shape));
  } else {
    return scratch_tensor(ctx, std::move(shape), static_cast<A*>(nullptr));
  }
}
// A tensor handed to the caller (may outlive the pass): an ordinary allocation (CUDA's
// `result_tensor`, which poisons it when tests ask for that).
template <class A, class B, class Ctx>
Tensor<A, B> new_result(Ctx& ctx, Shape shape) {
  if constexpr (is_host_backend<B>) {
    (void)ctx;
    return Tensor<A, B>(std::move(shape));
  } else {
    return result_tensor(ctx, std::move(shape), static_cast<A*>(nullptr));
  }
}
template <class A, class B, class Ctx>
Tensor<A, B> new_map(Ctx& ctx, const MapDims& d) {
  return new_tensor<A, B>(ctx, map_shape<B>(d));
}

// A copy of x in a new intermediate tensor.
template <class Ctx, class A, class B>
Tensor<A, B> copy_of(Ctx& ctx, const Tensor<A, B>& x) {
  if constexpr (is_host_backend<B>) {
    (void)ctx;
    return x.clone();
  } else {
    Tensor<A, B> y = new_tensor<A, B>(ctx, x.shape());
    copy(ctx, y, x);  // the backend's device-to-device copy
    return y;
  }
}

// A copy of x with elements of type TO (float <-> bf16 rounds to nearest even), in a new
// intermediate tensor.
template <class TO, class Ctx, class TI, class B>
Tensor<TO, B> converted(Ctx& ctx, const Tensor<TI, B>& x) {
  if constexpr (std::is_same_v<TO, TI>) {
    return copy_of(ctx, x);
  } else {
    Tensor<TO, B> y = new_tensor<TO, B>(ctx, x.shape());
    convert(ctx, x.data(), y.data(), x.numel());  // the backend's element-type conversion
    return y;
  }
}

// Public NCHW float32 (N, C, H, W) -> a map of B in its own order and type A. The CPU's maps
// already are that: the same tensor is returned (treat it as read-only).
template <class A, class Ctx, class B>
Tensor<A, B> map_from_nchw(Ctx& ctx, const Tensor<float, B>& x) {
  EPONA_CHECK(x.dim() == 4, "expected an (N, C, H, W) tensor, got ", shape_str(x.shape()));
  if constexpr (!channels_last_maps<B> && std::is_same_v<A, float>) {
    (void)ctx;
    return x;
  } else {
    const MapDims d{x.size(0), x.size(1), x.size(2), x.size(3)};
    Tensor<A, B> m = new_map<A, B>(ctx, d);
    transpose_last2(ctx, x.data(), m.data(), d.batch, d.channels, d.pixels());  // (N, C, HW) -> (N, HW, C)
    return m;
  }
}

// A map of B -> public NCHW float32, written into `out` (N, C, H, W) (a new allocation of the
// caller's, never an intermediate: results may outlive the pass).
template <class Ctx, class A, class B>
void map_to_nchw(Ctx& ctx, const Tensor<A, B>& m, Tensor<float, B>& out) {
  const MapDims d = map_dims(m, "map_to_nchw");
  check_shape(out, {d.batch, d.channels, d.height, d.width}, "map_to_nchw output");
  if constexpr (!channels_last_maps<B> && std::is_same_v<A, float>) {
    if (out.data() != m.data()) copy(ctx, m.data(), out.data(), m.numel());
  } else {
    transpose_last2(ctx, m.data(), out.data(), d.batch, d.pixels(), d.channels);  // (N, HW, C) -> (N, C, HW)
  }
}
template <class Ctx, class A, class B>
Tensor<float, B> map_to_nchw(Ctx& ctx, const Tensor<A, B>& m) {
  const MapDims d = map_dims(m, "map_to_nchw");
  Tensor<float, B> out = new_result<float, B>(ctx, {d.batch, d.channels, d.height, d.width});
  map_to_nchw(ctx, m, out);
  return out;
}

}  // namespace nn
}  // namespace epona
