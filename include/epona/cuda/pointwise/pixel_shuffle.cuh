// epona/cuda/pointwise/pixel_shuffle.cuh — the DC-AE's data movement on the GPU over channels-last maps,
// as cpu/pixel_shuffle.hpp: pixel (un)shuffle in torch's channel order with the averaging and
// duplicating shortcuts in the same pass (optionally accumulating into a residual), the
// upsampling pair shuffle(conv) + duplicating shortcut in one pass, and the (n, a, b) -> (n, b, a)
// transpose (with a type conversion) between NCHW and channels-last.
#pragma once

#include <algorithm>
#include <cstdint>

#include "epona/core/shapes.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace shuffle_detail {

// Geometry of a shuffle in the index type I (32-bit when everything fits: the kernels are
// bound by index arithmetic otherwise).
template <class I>
struct Geometry {
  I H, W, C, r, g_or_rep, Ho, Wo, Co;  // input extents, factor, group or repeat count, output extents
};

// out[n, yo, xo, k] (+)= (1/g) Σ_t x[n, r·yo + sub/r, r·xo + sub%r, cu/r²], cu = k·g + t, sub = cu % r².
// One thread per output element, consecutive threads along k.
template <class T, class I>
__global__ void unshuffle_kernel(const T* __restrict__ x, T* __restrict__ out, Geometry<I> q, I total, bool accumulate) {
  const I r2 = q.r * q.r, g = q.g_or_rep;
  for (I i = blockIdx.x * blockDim.x + threadIdx.x; i < total; i += gridDim.x * blockDim.x) {
    const I k = i % q.Co, pixel = i / q.Co;
    const I xo = pixel % q.Wo, rest = pixel / q.Wo, yo = rest % q.Ho, n = rest / q.Ho;
    float sum = 0.f;
    for (I t = 0; t < g; ++t) {
      const I cu = k * g + t, sub = cu % r2;
      sum += detail::to_f32(x[((n * q.H + q.r * yo + sub / q.r) * q.W + q.r * xo + sub % q.r) * q.C + cu / r2]);
    }
    float v = g == 1 ? sum : sum / static_cast<float>(g);
    if (accumulate) v += detail::to_f32(out[i]);
    out[i] = detail::from_f32<T>(v);
  }
}

// out[n, yo, xo, c] (+)= x[n, yo/r, xo/r, m/rep], m = c·r² + (yo%r)·r + xo%r. One thread per
// kVec consecutive output channels of one pixel (kVec = 8: 16-byte stores, the pixel's index
// arithmetic done once for the pack).
template <class T, class I, int kVec>
__global__ void shuffle_kernel(const T* __restrict__ x, T* __restrict__ out, Geometry<I> q, I total, bool accumulate) {
  const I rep = q.g_or_rep, packs = q.Co / kVec, items = total / kVec;
  for (I i = blockIdx.x * blockDim.x + threadIdx.x; i < items; i += gridDim.x * blockDim.x) {
    const I c0 = (i % packs) * kVec, pixel = i / packs;
    const I xo = pixel % q.Wo, rest = pixel / q.Wo, yo = rest % q.Ho, n = rest / q.Ho;
    const I sub = (yo % q.r) * q.r + xo % q.r;
    const T* src = x + ((n * q.H + yo / q.r) * q.W + xo / q.r) * q.C;
    float v[kVec];
#pragma unroll
    for (int j = 0; j < kVec; ++j) v[j] = detail::to_f32(src[((c0 + j) * q.r * q.r + sub) / rep]);
    T* dst = out + pixel * q.Co + c0;
    if constexpr (kVec == detail::kPack) {
      if (accumulate) {
        float o[kVec];
        detail::load8(dst, o);
#pragma unroll
        for (int j = 0; j < kVec; ++j) v[j] += o[j];
      }
      detail::store8(dst, v);
    } else {
      if (accumulate) v[0] += detail::to_f32(dst[0]);
      dst[0] = detail::from_f32<T>(v[0]);
    }
  }
}

// Launches kernel<T, I> with 32-bit indices when every index fits, 64-bit otherwise.
template <template <class, class> class Launch, class T>
void launch_shuffle(Context& ctx, const T* x, T* out, const Geometry<std::int64_t>& q, std::int64_t in_total,
                    std::int64_t out_total, bool accumulate) {
  if (out_total == 0) return;
  constexpr int threads = 256;
  const unsigned blocks = detail::grid_for(out_total, threads);
  if (std::max(in_total, out_total) < (std::int64_t{1} << 31)) {
    const auto c = [](std::int64_t v) { return static_cast<std::uint32_t>(v); };
    const Geometry<std::uint32_t> q32{c(q.H), c(q.W), c(q.C), c(q.r), c(q.g_or_rep), c(q.Ho), c(q.Wo), c(q.Co)};
    Launch<T, std::uint32_t>::run(blocks, threads, ctx.stream(), x, out, q32, c(out_total), accumulate);
  } else {
    Launch<T, std::int64_t>::run(blocks, threads, ctx.stream(), x, out, q, out_total, accumulate);
  }
  EPONA_CUDA_CHECK_LAUNCH();
}
template <class T, class I>
struct UnshuffleLaunch {
  static void run(unsigned b, int t, cudaStream_t s, const T* x, T* o, Geometry<I> q, I n, bool acc) {
    unshuffle_kernel<T, I><<<b, t, 0, s>>>(x, o, q, n, acc);
  }
};
template <class T, class I>
struct ShuffleLaunch {
  static void run(unsigned b, int t, cudaStream_t s, const T* x, T* o, Geometry<I> q, I n, bool acc) {
    if (q.Co % detail::kPack == 0 && detail::aligned16(o))
      shuffle_kernel<T, I, detail::kPack><<<std::max(1u, b / detail::kPack), t, 0, s>>>(x, o, q, n, acc);
    else
      shuffle_kernel<T, I, 1><<<b, t, 0, s>>>(x, o, q, n, acc);
  }
};

// The upsampling pair in one pass (r = 2): out[n, 2y+i, 2x+j, c] = round(main[n, y, x, 4c + s] +
// x[n, y, x, (4c + s)/kRep]), s = 2i + j. One thread per input pixel and 8 output channels: it
// reads main's 32 channels 4c0 … 4c0+31 and x's 32/kRep channels with 16-byte loads and writes
// the 4 output pixels' 8 channels with 16-byte stores.
template <class T, int kRep>
__global__ void shuffle2_duplicate_add_kernel(const T* __restrict__ main, const T* __restrict__ x, T* __restrict__ out,
                                              std::uint32_t H, std::uint32_t W, std::uint32_t Co,
                                              std::int64_t items) {
  constexpr int kP = detail::kPack, kMain = 4 * kP, kX = kMain / kRep;
  const std::uint32_t packs = Co / kP, Cm = 4 * Co, Cx = Cm / kRep;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < items;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::uint32_t c0 = static_cast<std::uint32_t>(i % packs) * kP;
    const std::int64_t pixel = i / packs;  // (n, y, x) of the input
    const std::int64_t xx = pixel % W, rest = pixel / W, y = rest % H, n = rest / H;
    float m[kMain], s[kX];
#pragma unroll
    for (int q = 0; q < kMain / kP; ++q) {
      float v[kP];
      detail::load8(main + pixel * Cm + 4 * c0 + q * kP, v);
#pragma unroll
      for (int e = 0; e < kP; ++e) m[q * kP + e] = v[e];
    }
#pragma unroll
    for (int q = 0; q < kX / kP; ++q) {
      float v[kP];
      detail::load8(x + pixel * Cx + 4 * c0 / kRep + q * kP, v);
#pragma unroll
      for (int e = 0; e < kP; ++e) s[q * kP + e] = v[e];
    }
#pragma unroll
    for (int sub = 0; sub < 4; ++sub) {
      float o[kP];
#pragma unroll
      for (int k = 0; k < kP; ++k) o[k] = m[4 * k + sub] + s[(4 * k + sub) / kRep];
      const std::int64_t opix = (n * 2 * H + 2 * y + sub / 2) * (2 * W) + 2 * xx + sub % 2;
      detail::store8(out + opix * Co + c0, o);
    }
  }
}

// out[n, c, y, x] = float(in[n, y/r, x/r, c·r² + (y%r)·r + x%r]): the decoder's last pixel shuffle
// written straight into the public NCHW float32 image. One thread per output element along x.
template <class T>
__global__ void shuffle_to_nchw_kernel(const T* __restrict__ in, float* __restrict__ out, std::uint32_t C,
                                       std::uint32_t Ho, std::uint32_t Wo, std::uint32_t r, std::int64_t total) {
  const std::uint32_t Cin = C * r * r, Wi = Wo / r, Hi = Ho / r;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::uint32_t xo = static_cast<std::uint32_t>(i % Wo);
    const std::int64_t rest = i / Wo;
    const std::uint32_t yo = static_cast<std::uint32_t>(rest % Ho);
    const std::int64_t nc = rest / Ho;
    const std::uint32_t c = static_cast<std::uint32_t>(nc % C);
    const std::int64_t n = nc / C;
    const std::int64_t src = ((n * Hi + yo / r) * Wi + xo / r) * Cin + c * r * r + (yo % r) * r + xo % r;
    out[i] = detail::to_f32(in[src]);
  }
}

template <class TI, class TO>
__global__ void transpose_kernel(const TI* __restrict__ x, TO* __restrict__ y, std::int64_t A, std::int64_t B) {
  __shared__ float tile[32][33];
  const std::int64_t n = blockIdx.z, a0 = std::int64_t{blockIdx.y} * 32, b0 = std::int64_t{blockIdx.x} * 32;
  const TI* xs = x + n * A * B;
  TO* ys = y + n * A * B;
  for (int i = threadIdx.y; i < 32; i += blockDim.y) {
    const std::int64_t a = a0 + i, b = b0 + threadIdx.x;
    if (a < A && b < B) tile[i][threadIdx.x] = detail::to_f32(xs[a * B + b]);
  }
  __syncthreads();
  for (int i = threadIdx.y; i < 32; i += blockDim.y) {
    const std::int64_t b = b0 + i, a = a0 + threadIdx.x;
    if (a < A && b < B) ys[b * A + a] = detail::from_f32<TO>(tile[threadIdx.x][i]);
  }
}

}  // namespace shuffle_detail

// x (N, H, W, C) channels-last -> out (N, H/r, W/r, channels_out) (+)= unshuffle(x), each output
// channel the mean of g = C·r²/channels_out consecutive unshuffled channels (g = 1: the plain
// unshuffle). Sums in float32, one rounding to T.
template <class T>
void pixel_unshuffle_average(Context& ctx, const T* x, T* out, const ShuffleShape& s, std::int64_t channels_out,
                             bool accumulate = false) {
  static_assert(is_device_float<T>, "pixel_unshuffle_average takes float or bf16");
  const std::int64_t r = s.factor, r2 = r * r;
  EPONA_CHECK(s.batch >= 0 && s.channels > 0 && s.height > 0 && s.width > 0 && r >= 1,
              "pixel_unshuffle: bad geometry N=", s.batch, " C=", s.channels, " H=", s.height, " W=", s.width,
              " r=", r);
  EPONA_CHECK(s.height % r == 0 && s.width % r == 0, "pixel_unshuffle: ", s.height, "x", s.width,
              " is not divisible by factor ", r);
  EPONA_CHECK(channels_out > 0 && (s.channels * r2) % channels_out == 0, "channel averaging: ", s.channels, "·", r2,
              " unshuffled channels do not split into ", channels_out, " groups");
  const std::int64_t Ho = s.height / r, Wo = s.width / r;
  const shuffle_detail::Geometry<std::int64_t> q{s.height, s.width, s.channels, r, s.channels * r2 / channels_out,
                                                 Ho, Wo, channels_out};
  shuffle_detail::launch_shuffle<shuffle_detail::UnshuffleLaunch>(
      ctx, x, out, q, s.batch * s.height * s.width * s.channels, s.batch * Ho * Wo * channels_out, accumulate);
}

// x (N, H, W, C) -> out (N, H·r, W·r, channels_out) (+)= shuffle(repeat_interleave(x, rep)),
// rep = channels_out·r²/C (rep = 1: the plain shuffle).
template <class T>
void pixel_shuffle_duplicate(Context& ctx, const T* x, T* out, const ShuffleShape& s, std::int64_t channels_out,
                             bool accumulate = false) {
  static_assert(is_device_float<T>, "pixel_shuffle_duplicate takes float or bf16");
  const std::int64_t r = s.factor, r2 = r * r;
  EPONA_CHECK(s.batch >= 0 && s.channels > 0 && s.height > 0 && s.width > 0 && r >= 1,
              "pixel_shuffle: bad geometry N=", s.batch, " C=", s.channels, " H=", s.height, " W=", s.width,
              " r=", r);
  EPONA_CHECK(channels_out > 0 && (channels_out * r2) % s.channels == 0, "channel duplication: ", channels_out, "·",
              r2, " shuffled channels are not a multiple of the ", s.channels, " input channels");
  const shuffle_detail::Geometry<std::int64_t> q{s.height, s.width, s.channels, r, channels_out * r2 / s.channels,
                                                 s.height * r, s.width * r, channels_out};
  shuffle_detail::launch_shuffle<shuffle_detail::ShuffleLaunch>(ctx, x, out, q, s.batch * s.height * s.width * s.channels,
                                                                s.batch * s.height * r * s.width * r * channels_out,
                                                                accumulate);
}

// The upsampling pair y = shuffle_2(main) + D(x; C_out, 2) in one pass: main (N, H, W, 4·C_out)
// (the conv's output), x (N, H, W, C_x) with 4·C_out / C_x = 2 or 4, out (N, 2H, 2W, C_out).
// Same rounding as the two passes (round(main + x): main is already rounded, the shuffle and the
// duplication are copies). False (nothing done) for other geometries, unaligned pointers or
// with the DC-AE fusions off: then run pixel_shuffle_duplicate twice.
template <class T>
bool pixel_shuffle_add_duplicate_fused(Context& ctx, const T* main, const T* x, T* out, const ShuffleShape& s,
                                 std::int64_t channels_out, std::int64_t x_channels) {
  static_assert(is_device_float<T>, "pixel_shuffle_add_duplicate_fused takes float or bf16");
  if (!ctx.policy().dcae_fusion || s.factor != 2 || channels_out % detail::kPack != 0 || x_channels <= 0 ||
      s.channels != 4 * channels_out || (4 * channels_out) % x_channels != 0 || x_channels % detail::kPack != 0)
    return false;
  const std::int64_t rep = 4 * channels_out / x_channels;
  if ((rep != 2 && rep != 4) || !detail::aligned16(main) || !detail::aligned16(x) || !detail::aligned16(out) ||
      std::max({s.height, s.width, s.channels}) >= (std::int64_t{1} << 31))
    return false;
  const std::int64_t items = s.batch * s.height * s.width * (channels_out / detail::kPack);
  if (items == 0) return true;
  const auto u32 = [](std::int64_t v) { return static_cast<std::uint32_t>(v); };
  const unsigned blocks = detail::grid_for(items, 256);
  if (rep == 2)
    shuffle_detail::shuffle2_duplicate_add_kernel<T, 2><<<blocks, 256, 0, ctx.stream()>>>(
        main, x, out, u32(s.height), u32(s.width), u32(channels_out), items);
  else
    shuffle_detail::shuffle2_duplicate_add_kernel<T, 4><<<blocks, 256, 0, ctx.stream()>>>(
        main, x, out, u32(s.height), u32(s.width), u32(channels_out), items);
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

// F.pixel_shuffle(x, r) of a channels-last map x (N, H, W, C·r²) written as NCHW float32
// (N, C, H·r, W·r) in one pass (a plain copy per element, no rounding: what the shuffle and the
// layout change give). False (nothing done) with the DC-AE fusions off or extents past 32 bits.
template <class T>
bool pixel_shuffle_to_nchw_fused(Context& ctx, const T* x, float* out, std::int64_t N, std::int64_t C, std::int64_t H,
                                 std::int64_t W, std::int64_t r) {
  static_assert(is_device_float<T>, "pixel_shuffle_to_nchw_fused takes float or bf16");
  EPONA_CHECK(N >= 0 && C > 0 && H > 0 && W > 0 && r >= 1, "pixel_shuffle_to_nchw: bad extents");
  if (!ctx.policy().dcae_fusion || std::max({C * r * r, H * r, W * r}) >= (std::int64_t{1} << 31)) return false;
  const std::int64_t total = N * C * H * r * W * r;
  if (total == 0) return true;
  const auto u32 = [](std::int64_t v) { return static_cast<std::uint32_t>(v); };
  shuffle_detail::shuffle_to_nchw_kernel<<<detail::grid_for(total, 256), 256, 0, ctx.stream()>>>(
      x, out, u32(C), u32(H * r), u32(W * r), u32(r), total);
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

// y[n, j, i] = x[n, i, j] for x (N, A, B): NCHW (N, C, HW) <-> channels-last (N, HW, C), with
// the element type converted (float <-> bf16 rounds to nearest even).
template <class TI, class TO>
void transpose_last2(Context& ctx, const TI* x, TO* y, std::int64_t N, std::int64_t A, std::int64_t B) {
  static_assert(is_device_float<TI> && is_device_float<TO>, "transpose_last2 takes float or bf16");
  EPONA_CHECK(N >= 0 && A >= 0 && B >= 0, "transpose_last2: negative extent");
  EPONA_CHECK(N <= 65535 && (A + 31) / 32 <= 65535 && (B + 31) / 32 <= 0x7fffffff,
              "transpose_last2: (", N, ", ", A, ", ", B, ") exceeds one launch");
  if (N == 0 || A == 0 || B == 0) return;
  const dim3 grid(static_cast<unsigned>((B + 31) / 32), static_cast<unsigned>((A + 31) / 32), static_cast<unsigned>(N));
  shuffle_detail::transpose_kernel<<<grid, dim3(32, 8), 0, ctx.stream()>>>(x, y, A, B);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda
