// epona/cuda/pointwise/norm.cuh — normalisations over the last dimension on the GPU: LayerNorm (affine
// or not), LayerNorm fused with adaLN modulation ((1 + scale) * LN(x) + shift, the DiT blocks:
// one pass instead of three), the residual update fused with the LayerNorm after it (x += [gate ⊙]
// y, then LN(x): the MST's `x + branch` before ln2 / the next ln1, the DiTs' gated residual before
// the next modulated norm; one pass over the residual stream instead of two) and per-head RMSNorm
// (the DiTs' QK-norm, in place on packed QKV). Statistics in float32 (two-pass mean/variance,
// biased variance, as torch.layer_norm).
#pragma once

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "epona/core/kernel_options.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/pointwise/elementwise.cuh"

namespace epona::cuda {

namespace detail {

// Mean and 1/sqrt(var + eps) of one row, computed by the whole block (two passes over x).
template <class TX>
__device__ void row_moments(const TX* x, std::int64_t n, float eps, float& mean, float& rstd, float* scratch) {
  float s = 0;
  for (std::int64_t i = threadIdx.x; i < n; i += blockDim.x) s += to_f32(x[i]);
  mean = block_sum(s, scratch) / static_cast<float>(n);
  float v = 0;
  for (std::int64_t i = threadIdx.x; i < n; i += blockDim.x) {
    const float d = to_f32(x[i]) - mean;
    v += d * d;
  }
  rstd = 1.0f / sqrtf(block_sum(v, scratch) / static_cast<float>(n) + eps);
}

// One block per row. Affine LayerNorm when weight/bias are given; with modulate, shift/scale
// take their place as (1 + scale) * LN(x) + shift, 1 + scale rounded to the parameters'
// storage type as PyTorch does for `1 + scale_tensor`.
template <class TX, class TY, class TP, bool Modulate>
__global__ void layer_norm_kernel(const TX* x, TY* y, std::int64_t n, const TP* mul, const TP* add, float eps) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  __shared__ float scratch[32];
  const TX* xr = x + blockIdx.x * n;
  TY* yr = y + blockIdx.x * n;
  float mean, rstd;
  row_moments(xr, n, eps, mean, rstd, scratch);
  for (std::int64_t i = threadIdx.x; i < n; i += blockDim.x) {
    float v = (to_f32(xr[i]) - mean) * rstd;
    if constexpr (Modulate) {
      v = round_to<TP>(1.0f + to_f32(mul[i])) * v + to_f32(add[i]);
    } else {
      if (mul) v = v * to_f32(mul[i]);
      if (add) v = v + to_f32(add[i]);
    }
    yr[i] = from_f32<TY>(v);
  }
}

// The row held in registers (read once, written once, 16-byte accesses), for n % 8 == 0 and
// aligned rows: pack k of a row's worker is pack first + k·step. With Residual, the row is
// first updated and written back: x = round_TX(x + [round(gate ⊙)] y), exactly what add_inplace /
// add_gated store; the statistics are then taken over the stored values, as the unfused pair.
template <class TX, class TY, class TG, class TO, class TP>
struct RowNormArgs {
  const TX* x;     // rows of the input (the residual before its update)
  TX* x_out;       // where the updated residual goes (Residual only; may be x)
  const TY* y;     // the branch added to x (Residual only)
  const TG* gate;  // per-column gate of the branch, or null
  TO* out;         // LN output (may alias x when there is no residual)
  const TP* mul;   // weight, or scale with Modulate (may be null without Modulate)
  const TP* add;   // bias, or shift with Modulate
  std::int64_t rows, n;
  float eps;
  bool reverse = false;  // the warp-per-row kernel walks the rows last to first
  NormItems items{};     // rows of several items (items.count > 1): `rows` is their total
};

// What norm_row does to a pack of its float32 results (channels c0..c0+7) before storing it:
// nothing, unless a caller fuses a per-channel transform (the MST's RoPE) so the row is rounded
// to its storage type once.
struct KeepPack {
  __device__ void operator()(float (&)[kPack], int) const {}
};

// One row by one worker (a warp or a block) of up to P packs per thread; `sum` reduces over the
// worker. Affine LayerNorm when weight/bias are given; with Modulate, shift/scale take their
// place as (1 + scale) * LN(x) + shift, 1 + scale rounded to the parameters' storage type as
// PyTorch does for `1 + scale_tensor`. `finish` transforms each pack before it is stored, into
// row `out_row` of out (row when negative).
template <int P, bool Modulate, bool Residual, class TX, class TY, class TG, class TO, class TP, class Sum,
          class Finish = KeepPack>
__device__ __forceinline__ void norm_row(const RowNormArgs<TX, TY, TG, TO, TP>& a, std::int64_t row, int first,
                                         int step, Sum sum, Finish finish = {}, std::int64_t out_row = -1) {
  const int packs = static_cast<int>(a.n / kPack);
  std::int64_t x_row = row, at_row = row, mod = 0;  // the item's input row, its output row, its vectors
  if (a.items.count > 1) {
    const std::int64_t item = row / a.items.rows, r = row % a.items.rows;
    x_row = item * a.items.x_stride + r;
    at_row = item * a.items.stride + r;
    mod = item * a.items.mod_stride;
  }
  const std::int64_t x_base = x_row * a.n, base = at_row * a.n, out_base = (out_row < 0 ? at_row : out_row) * a.n;
  float v[P][kPack];
#pragma unroll
  for (int k = 0; k < P; ++k)
    if (first + k * step < packs) load8(a.x + x_base + (first + k * step) * kPack, v[k]);
  if constexpr (Residual) {
#pragma unroll
    for (int k = 0; k < P; ++k) {
      const int p = first + k * step;
      if (p >= packs) continue;
      float ys[kPack], gs[kPack];
      load8(a.y + base + p * kPack, ys);
      if (a.gate) load8(a.gate + mod + p * kPack, gs);
#pragma unroll
      for (int i = 0; i < kPack; ++i)
        v[k][i] = round_to<TX>(v[k][i] + (a.gate ? round_to<promote_t<TG, TY>>(gs[i] * ys[i]) : ys[i]));
      store8(a.x_out + base + p * kPack, v[k]);
    }
  }
  float s = 0;
#pragma unroll
  for (int k = 0; k < P; ++k)
    if (first + k * step < packs)
#pragma unroll
      for (int i = 0; i < kPack; ++i) s += v[k][i];
  const float mean = sum(s) / static_cast<float>(a.n);
  float q = 0;
#pragma unroll
  for (int k = 0; k < P; ++k)
    if (first + k * step < packs)
#pragma unroll
      for (int i = 0; i < kPack; ++i) q += (v[k][i] - mean) * (v[k][i] - mean);
  const float rstd = 1.0f / sqrtf(sum(q) / static_cast<float>(a.n) + a.eps);
#pragma unroll
  for (int k = 0; k < P; ++k) {
    const int p = first + k * step;
    if (p >= packs) continue;
    float m[kPack], b[kPack];
    if (a.mul) load8(a.mul + mod + p * kPack, m);
    if (a.add) load8(a.add + mod + p * kPack, b);
#pragma unroll
    for (int i = 0; i < kPack; ++i) {
      float o = (v[k][i] - mean) * rstd;
      if constexpr (Modulate) {
        o = round_to<TP>(1.0f + m[i]) * o + b[i];
      } else {
        if (a.mul) o = o * m[i];
        if (a.add) o = o + b[i];
      }
      v[k][i] = o;
    }
    finish(v[k], p * kPack);
    store8(a.out + out_base + p * kPack, v[k]);
  }
}

// One block per row, up to kRowPacks packs per thread (n <= 8 * kRowPacks * 256): many threads
// per row, for few rows (the DiTs' 15 to 1027), where a warp per row leaves the GPU idle.
constexpr int kRowPacks = 4;
template <class TX, class TY, class TG, class TO, class TP, bool Modulate, bool Residual>
__global__ void row_norm_block_kernel(RowNormArgs<TX, TY, TG, TO, TP> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  __shared__ float scratch[32];
  norm_row<kRowPacks, Modulate, Residual>(a, blockIdx.x, threadIdx.x, blockDim.x,
                                          [&](float v) { return block_sum(v, scratch); });
}

// One warp per row (n <= 8 * 32 * P), kNormWarps rows per block: no block barriers, for many
// rows (the MST's 5150), where every row of the grid is in flight at once.
constexpr int kNormWarps = 4;
template <class TX, class TY, class TG, class TO, class TP, int P, bool Modulate, bool Residual>
__global__ void __launch_bounds__(32 * kNormWarps) row_norm_warp_kernel(RowNormArgs<TX, TY, TG, TO, TP> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t row = blockIdx.x * std::int64_t{kNormWarps} + threadIdx.x / 32;
  if (row >= a.rows) return;
  norm_row<P, Modulate, Residual>(a, pass_index(row, a.rows, a.reverse), threadIdx.x & 31, 32,
                                  [](float v) { return warp_sum(v); });
}

// Widest row the warp kernel holds (8 packs of 8 per lane), and the fewest rows for which it
// beats a block per row (measured on the H200: 515 rows of 1024 ran 40 % slower by warp).
constexpr std::int64_t kWarpRowMax = 8 * 32 * kPack;
inline std::int64_t warp_rows_min(const Context& ctx) { return 8 * std::int64_t{ctx.info().multiprocessors}; }

// Calls f(std::integral_constant<int, P>{}) with the packs per lane P (1, 2, 4 or 8) the
// warp-per-row kernels use for rows of n elements (n <= kWarpRowMax): the fewest that hold a row.
template <class F>
void with_warp_row_packs(std::int64_t n, F&& f) {
  const std::int64_t per_lane = (n / kPack + 31) / 32;
  if (per_lane <= 1) f(std::integral_constant<int, 1>{});
  else if (per_lane <= 2) f(std::integral_constant<int, 2>{});
  else if (per_lane <= 4) f(std::integral_constant<int, 4>{});
  else f(std::integral_constant<int, 8>{});
}

template <int P, bool Modulate, bool Residual, class TX, class TY, class TG, class TO, class TP>
void launch_row_norm_warp(Context& ctx, RowNormArgs<TX, TY, TG, TO, TP> a) {
  const auto blocks = static_cast<unsigned>((a.rows + kNormWarps - 1) / kNormWarps);
  a.reverse = ctx.policy().reversed_passes;
  launch_after(row_norm_warp_kernel<TX, TY, TG, TO, TP, P, Modulate, Residual>, blocks, 32 * kNormWarps, 0, ctx,
               a);
}

// The register-resident kernels (warp or block per row) when the rows are packable and fit;
// false when neither applies (the caller then takes the general path).
template <bool Modulate, bool Residual, class TX, class TY, class TG, class TO, class TP>
bool try_row_norm_packed(Context& ctx, const RowNormArgs<TX, TY, TG, TO, TP>& a) {
  const std::int64_t n = a.n, packs = n / kPack;
  if (!packable(a.x, n, n) || !packable(a.x_out, n, n) || !packable(a.y, n, n) || !packable(a.gate, n, 0) ||
      !packable(a.out, n, n) || !packable(a.mul, n, 0) || !packable(a.add, n, 0))
    return false;
  if (n <= kWarpRowMax && a.rows >= warp_rows_min(ctx)) {
    with_warp_row_packs(n, [&](auto packs_per_lane) {
      launch_row_norm_warp<decltype(packs_per_lane)::value, Modulate, Residual>(ctx, a);
    });
  } else if (packs <= 256 * kRowPacks) {
    const int threads = static_cast<int>(std::min<std::int64_t>(256, (packs + 31) / 32 * 32));
    launch_after(row_norm_block_kernel<TX, TY, TG, TO, TP, Modulate, Residual>, static_cast<unsigned>(a.rows), threads,
                 0, ctx, a);
  } else {
    return false;
  }
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

// One warp per (token, head).
template <class T, class TP>
__global__ void rms_norm_heads_kernel(T* x, std::int64_t rows, std::int64_t row_stride, int heads, int head_dim,
                                      const TP* scale, float eps) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;
  if (item >= rows * heads) return;
  const int lane = threadIdx.x & 31;
  T* p = x + (item / heads) * row_stride + (item % heads) * head_dim;
  float ss = 0;
  for (int i = lane; i < head_dim; i += 32) {
    const float v = to_f32(p[i]);
    ss += v * v;
  }
  const float rr = 1.0f / sqrtf(warp_sum(ss) / static_cast<float>(head_dim) + eps);
  // Official QK-norm: (x * rrms).to(x.dtype) * scale — the product is rounded before scaling.
  for (int i = lane; i < head_dim; i += 32) p[i] = from_f32<T>(round_to<T>(to_f32(p[i]) * rr) * to_f32(scale[i]));
}

inline int norm_threads(std::int64_t n) { return n >= 1024 ? 256 : n >= 256 ? 128 : 64; }

template <bool Modulate, class TX, class TY, class TP>
void launch_layer_norm(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const TP* mul,
                       const TP* add, float eps, const char* what) {
  static_assert(is_device_float<TX> && is_device_float<TY> && is_device_float<TP>, "norms take float or bf16");
  EPONA_CHECK(rows >= 0 && n > 0, what, ": bad extent (rows ", rows, ", width ", n, ")");
  EPONA_CHECK(rows <= 0x7fffffff, what, ": ", rows, " rows exceed one launch");
  if (rows == 0) return;
  const RowNormArgs<TX, TX, TX, TY, TP> args{x, nullptr, nullptr, nullptr, y, mul, add, rows, n, eps};
  if (try_row_norm_packed<Modulate, false>(ctx, args)) return;
  launch_after(layer_norm_kernel<TX, TY, TP, Modulate>, static_cast<unsigned>(rows), norm_threads(n), 0, ctx, x,
               y, n, mul, add, eps);
}

// x_out = x + [gate ⊙] y, then out = LN(x_out) (affine or modulated): one pass where a
// register-resident kernel applies, else a copy (x_out != x), the residual kernel and the
// LayerNorm one after the other. x_out is x or a buffer that does not overlap it.
template <bool Modulate, class TX, class TY, class TG, class TO, class TP>
void launch_residual_norm(Context& ctx, const TX* x_in, TX* x, const TY* y, const TG* gate, TO* out,
                          std::int64_t rows, std::int64_t n, const TP* mul, const TP* add, float eps,
                          const char* what) {
  static_assert(is_device_float<TX> && is_device_float<TY> && is_device_float<TG> && is_device_float<TO> &&
                    is_device_float<TP>,
                "norms take float or bf16");
  EPONA_CHECK(x_in != nullptr && x != nullptr && y != nullptr && out != nullptr, what,
              ": null residual, branch or output");
  EPONA_CHECK(rows >= 0 && n > 0, what, ": bad extent (rows ", rows, ", width ", n, ")");
  EPONA_CHECK(rows <= 0x7fffffff, what, ": ", rows, " rows exceed one launch");
  if (rows == 0) return;
  const RowNormArgs<TX, TY, TG, TO, TP> args{x_in, x, y, gate, out, mul, add, rows, n, eps};
  if (try_row_norm_packed<Modulate, true>(ctx, args)) return;
  if (x_in != x)
    EPONA_CUDA_CHECK(cudaMemcpyAsync(x, x_in, static_cast<std::size_t>(rows * n) * sizeof(TX),
                                     cudaMemcpyDeviceToDevice, ctx.stream()));
  add_rows(ctx, x, y, gate, rows, n, what);
  launch_layer_norm<Modulate>(ctx, static_cast<const TX*>(x), out, rows, n, mul, add, eps, what);
}

}  // namespace detail

// y[m, :] = (x[m, :] - mean) * rstd * weight + bias over rows of width n. weight/bias may be
// null (no affine). x and y may alias.
template <class TX, class TY, class TP = float>
void layer_norm(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const TP* weight,
                const std::type_identity_t<TP>* bias, float eps) {
  detail::launch_layer_norm<false>(ctx, x, y, rows, n, weight, bias, eps, "layer_norm");
}

// y = (1 + scale) * LN(x) + shift, LN without affine; shift/scale of width n, shared by all rows.
template <class TX, class TY, class TP>
void layer_norm_modulate(Context& ctx, const TX* x, TY* y, std::int64_t rows, std::int64_t n, const TP* shift,
                         const TP* scale, float eps) {
  EPONA_CHECK(shift != nullptr && scale != nullptr, "layer_norm_modulate: null shift or scale");
  detail::launch_layer_norm<true>(ctx, x, y, rows, n, scale, shift, eps, "layer_norm_modulate");
}

// x[r, :] += y[r, :], then out[r, :] = LN(x[r, :]) * weight + bias (weight/bias may be null):
// the MST's float32 residual update followed by the next LayerNorm into the GEMM type.
// out must not overlap x or y.
template <class TX, class TY, class TO, class TP = float>
void add_layer_norm(Context& ctx, TX* x, const TY* y, TO* out, std::int64_t rows, std::int64_t n, const TP* weight,
                    const std::type_identity_t<TP>* bias, float eps) {
  detail::launch_residual_norm<false>(ctx, static_cast<const TX*>(x), x, y, static_cast<const TX*>(nullptr), out, rows,
                                      n, weight, bias, eps, "add_layer_norm");
}

// x_out[r, :] = x[r, :] + gate[:] ⊙ y[r, :] (as add_gated), then out = (1 + scale) * LN(x_out) +
// shift (as layer_norm_modulate): a DiT sublayer's gated residual and the next sublayer's
// modulated norm. x_out is x, or a buffer that does not overlap it (a DiT's first block reads
// its step-invariant condition rows where cond_in left them instead of a per-step copy).
template <class TX, class TY, class TG, class TO, class TP>
void add_gated_layer_norm_modulate(Context& ctx, const TX* x, TX* x_out, const TY* y, const TG* gate, TO* out,
                                   std::int64_t rows, std::int64_t n, const TP* shift, const TP* scale, float eps) {
  EPONA_CHECK(gate != nullptr && shift != nullptr && scale != nullptr,
              "add_gated_layer_norm_modulate: null gate, shift or scale");
  detail::launch_residual_norm<true>(ctx, x, x_out, y, gate, out, rows, n, scale, shift, eps,
                                     "add_gated_layer_norm_modulate");
}

// The same in place: x[r, :] += gate[:] ⊙ y[r, :], then out = (1 + scale) * LN(x) + shift.
template <class TX, class TY, class TG, class TO, class TP>
void add_gated_layer_norm_modulate(Context& ctx, TX* x, const TY* y, const TG* gate, TO* out, std::int64_t rows,
                                   std::int64_t n, const TP* shift, const TP* scale, float eps) {
  add_gated_layer_norm_modulate(ctx, static_cast<const TX*>(x), x, y, gate, out, rows, n, shift, scale, eps);
}

// layer_norm_modulate over the same rows of several items (NormItems: x and y are item 0's first
// row, shift and scale its vectors) in one launch where the register-resident kernels apply,
// else item by item.
template <class TX, class TY, class TP>
void layer_norm_modulate_items(Context& ctx, const TX* x, TY* y, std::int64_t n, const TP* shift, const TP* scale,
                               float eps, const NormItems& items) {
  EPONA_CHECK(shift != nullptr && scale != nullptr, "layer_norm_modulate_items: null shift or scale");
  EPONA_CHECK(items.count >= 1 && items.rows >= 0 && n > 0 && items.count * items.rows <= 0x7fffffff,
              "layer_norm_modulate_items: bad extent (", items.count, " items of ", items.rows, " rows, width ", n, ")");
  detail::RowNormArgs<TX, TX, TX, TY, TP> args{x, nullptr, nullptr, nullptr, y, scale, shift, items.count * items.rows, n, eps};
  args.items = items;
  if (items.count > 1 && args.rows > 0 && detail::try_row_norm_packed<true, false>(ctx, args)) return;
  for (std::int64_t b = 0; b < items.count; ++b)
    layer_norm_modulate(ctx, x + b * items.x_stride * n, y + b * items.stride * n, items.rows, n,
                        shift + b * items.mod_stride, scale + b * items.mod_stride, eps);
}

// add_gated_layer_norm_modulate (x read from x, the update written to x_out) over the same rows
// of several items, likewise in one launch where it can.
template <class TX, class TY, class TG, class TO, class TP>
void add_gated_layer_norm_modulate_items(Context& ctx, const TX* x, TX* x_out, const TY* y, const TG* gate, TO* out,
                                         std::int64_t n, const TP* shift, const TP* scale, float eps,
                                         const NormItems& items) {
  EPONA_CHECK(gate != nullptr && shift != nullptr && scale != nullptr && x != nullptr && x_out != nullptr &&
                  y != nullptr && out != nullptr,
              "add_gated_layer_norm_modulate_items: a null pointer");
  EPONA_CHECK(items.count >= 1 && items.rows >= 0 && n > 0 && items.count * items.rows <= 0x7fffffff,
              "add_gated_layer_norm_modulate_items: bad extent (", items.count, " items of ", items.rows, " rows, width ",
              n, ")");
  detail::RowNormArgs<TX, TY, TG, TO, TP> args{x, x_out, y, gate, out, scale, shift, items.count * items.rows, n, eps};
  args.items = items;
  if (items.count > 1 && args.rows > 0 && detail::try_row_norm_packed<true, true>(ctx, args)) return;
  for (std::int64_t b = 0; b < items.count; ++b) {
    const std::int64_t at = b * items.stride * n, m = b * items.mod_stride;
    add_gated_layer_norm_modulate(ctx, x + b * items.x_stride * n, x_out + at, y + at, gate + m, out + at, items.rows,
                                  n, shift + m, scale + m, eps);
  }
}

// In place, per token and head: x_h = x_h * rsqrt(mean(x_h^2) + eps) * scale, where token r's
// heads start at x + r * row_stride and are head_dim wide, `heads` of them side by side.
template <class T, class TP>
void rms_norm_heads(Context& ctx, T* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                    std::int64_t head_dim, const TP* scale, float eps) {
  static_assert(is_device_float<T> && is_device_float<TP>, "rms_norm_heads takes float or bf16");
  EPONA_CHECK(rows >= 0 && heads > 0 && head_dim > 0 && head_dim <= 0x7fffffff && heads <= 0x7fffffff,
              "rms_norm_heads: bad extent (rows ", rows, ", heads ", heads, ", head_dim ", head_dim, ")");
  EPONA_CHECK(row_stride >= heads * head_dim, "rms_norm_heads: row stride ", row_stride, " is narrower than ",
              heads, " heads of ", head_dim);
  EPONA_CHECK(scale != nullptr, "rms_norm_heads: null scale");
  if (rows == 0) return;
  constexpr int threads = 256, warps = threads / 32;
  const std::int64_t blocks = (rows * heads + warps - 1) / warps;
  EPONA_CHECK(blocks <= 0x7fffffff, "rms_norm_heads: ", rows * heads, " heads exceed one launch");
  detail::launch_after(detail::rms_norm_heads_kernel<T, TP>, static_cast<unsigned>(blocks), threads, 0, ctx, x, rows,
                       row_stride, static_cast<int>(heads), static_cast<int>(head_dim), scale, eps);
}

}  // namespace epona::cuda
