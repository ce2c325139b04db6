// epona/cuda/attention/lite_mla.cuh — LiteMLA's ReLU linear attention on the GPU over channels-last maps,
// as cpu::relu_linear_attention: per (image, head) the (d+1) x d matrix [v; 1]·relu(k)ᵀ is reduced
// over pixels (per-chunk partial sums, then a fixed-order sum: deterministic), then applied to
// relu(q) per pixel; or the quadratic order for small maps. float32 arithmetic throughout.
#pragma once

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "epona/core/shapes.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/runtime/scratch.hpp"

namespace epona::cuda {

namespace mla_detail {

constexpr int kMaxDim = 32;        // head dims up to one warp
constexpr int kThreads = 256;
constexpr int kTile = 64;          // pixels staged in shared memory per step

// Element (pixel p, channel c) of the per-head groups: q at 3·d·a + j, k at +d, v at +2d.
struct Geometry {
  std::int64_t pixels;  // per image
  int heads, d;
  __host__ __device__ std::int64_t row() const { return 3 * std::int64_t{heads} * d; }  // qkv channels per pixel
};

__device__ __forceinline__ float relu(float v) { return v > 0.f ? v : 0.f; }

// Up to 8 values (as float32, zero past `left`) of a head's q, k or v from p: one 16-byte load
// when kPacked (d a multiple of 8, rows 16-byte aligned), else element by element.
template <bool kPacked, class T>
__device__ __forceinline__ void load_pack(const T* p, int left, float (&v)[detail::kPack]) {
  if constexpr (kPacked) {
    detail::load8(p, v);
  } else {
#pragma unroll
    for (int j = 0; j < detail::kPack; ++j) v[j] = j < left ? detail::to_f32(p[j]) : 0.f;
  }
}

// d values of one pixel's q, k or v (float32, zero past d).
template <bool kPacked, class T>
__device__ __forceinline__ void load_head(const T* p, int d, float (&v)[kMaxDim]) {
#pragma unroll
  for (int j0 = 0; j0 < kMaxDim; j0 += detail::kPack) {
    float part[detail::kPack] = {};
    if (j0 < d) load_pack<kPacked>(p + j0, d - j0, part);
#pragma unroll
    for (int j = 0; j < detail::kPack; ++j) v[j0 + j] = part[j];
  }
}

// grid (chunks, heads, images): partial[(img, head, chunk)][i·d + j] = Σ_p vrow_i(p) relu(k_j(p))
// over the chunk's pixels in order, with vrow_d = 1 (the ones row: the normaliser's Σ_p relu(k_j)).
// Tiles of kTile pixels go through shared memory (16-byte loads of 8 channels per thread);
// thread t then owns row i = t / 8 and columns 4(t % 8) … +3 (threads 0-7 also the ones row).
template <class T, bool kPacked>
__global__ void __launch_bounds__(kThreads) partial_kernel(const T* __restrict__ qkv, float* __restrict__ partial,
                                                           Geometry g, std::int64_t chunk_pixels) {
  constexpr int kRow = kMaxDim + 4, kPacks = kMaxDim / detail::kPack;  // rows padded: conflict-free stores
  __shared__ __align__(16) float ks[kTile][kRow];
  __shared__ __align__(16) float vs[kTile][kRow];
  const int d = g.d, a = blockIdx.y, chunk = blockIdx.x, chunks = gridDim.x, t = threadIdx.x;
  const std::int64_t img = blockIdx.z;
  const T* base = qkv + img * g.pixels * g.row() + 3 * std::int64_t{a} * d;
  const std::int64_t p_begin = chunk * chunk_pixels, p_end = std::min(g.pixels, p_begin + chunk_pixels);
  const int i = t / 8, j0 = 4 * (t % 8);
  float acc[4] = {}, ones[4] = {};
  for (std::int64_t t0 = p_begin; t0 < p_end; t0 += kTile) {
    const int n = static_cast<int>(std::min<std::int64_t>(kTile, p_end - t0));
    for (int u = t; u < 2 * kTile * kPacks; u += kThreads) {  // unit u: 8 channels of one pixel's k or v
      const int c8 = (u % kPacks) * detail::kPack, p = (u / kPacks) % kTile;
      const bool is_v = u >= kTile * kPacks;
      float v[detail::kPack] = {};
      if (p < n && c8 < d) load_pack<kPacked>(base + (t0 + p) * g.row() + (is_v ? 2 * d : d) + c8, d - c8, v);
      float* dst = (is_v ? vs[p] : ks[p]) + c8;
#pragma unroll
      for (int e = 0; e < detail::kPack; ++e) dst[e] = is_v ? v[e] : relu(v[e]);
    }
    __syncthreads();
    for (int p = 0; p < n; ++p) {
      const float4 k4 = *reinterpret_cast<const float4*>(&ks[p][j0]);
      const float vi = vs[p][i];
      acc[0] += vi * k4.x, acc[1] += vi * k4.y, acc[2] += vi * k4.z, acc[3] += vi * k4.w;
      if (t < 8) ones[0] += k4.x, ones[1] += k4.y, ones[2] += k4.z, ones[3] += k4.w;
    }
    __syncthreads();
  }
  float* out = partial + ((img * gridDim.y + a) * chunks + chunk) * std::int64_t{(d + 1) * d};
#pragma unroll
  for (int e = 0; e < 4; ++e) {
    const int j = j0 + e;
    if (i < d && j < d) out[i * d + j] = acc[e];
    if (t < 8 && j < d) out[d * d + j] = ones[e];
  }
}

// m[(img, head)][e] = Σ_chunk partial[(img, head, chunk)][e], chunks in order.
// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void reduce_kernel(const float* __restrict__ partial, float* __restrict__ m, std::int64_t matrices,
                              int chunks, int entries) {
  const std::int64_t total = matrices * entries;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::int64_t mat = i / entries;
    const int e = static_cast<int>(i % entries);
    float s = 0.f;
    for (int c = 0; c < chunks; ++c) s += partial[(mat * chunks + c) * entries + e];
    m[i] = s;
  }
}

// grid (pixel blocks, heads, images), one thread per pixel: out_i = Σ_j M[i][j] relu(q_j) /
// (Σ_j M[d][j] relu(q_j) + eps), M of the block's head in shared memory (read as broadcasts).
template <class T, bool kPacked>
__global__ void __launch_bounds__(kThreads) apply_kernel(const T* __restrict__ qkv, const float* __restrict__ m,
                                                         T* __restrict__ out, Geometry g, float eps) {
  __shared__ __align__(16) float ms[kMaxDim + 1][kMaxDim];
  const int d = g.d, a = blockIdx.y;
  const std::int64_t img = blockIdx.z;
  const float* mat = m + (img * gridDim.y + a) * std::int64_t{(d + 1) * d};
  for (int e = threadIdx.x; e < (kMaxDim + 1) * kMaxDim; e += blockDim.x) {
    const int i = e / kMaxDim, j = e % kMaxDim;
    ms[i][j] = (i < d || i == kMaxDim) && j < d ? mat[(i == kMaxDim ? d : i) * d + j] : 0.f;
  }
  __syncthreads();
  const std::int64_t p = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x;
  if (p >= g.pixels) return;
  float q[kMaxDim];
  load_head<kPacked>(qkv + img * g.pixels * g.row() + p * g.row() + 3 * std::int64_t{a} * d, d, q);
#pragma unroll
  for (int j = 0; j < kMaxDim; ++j) q[j] = relu(q[j]);
  const auto dot = [&](int i) {
    float s = 0.f;
#pragma unroll
    for (int j = 0; j < kMaxDim; j += 4) {
      const float4 w = *reinterpret_cast<const float4*>(&ms[i][j]);
      s += w.x * q[j] + w.y * q[j + 1] + w.z * q[j + 2] + w.w * q[j + 3];
    }
    return s;
  };
  const float den = dot(kMaxDim) + eps;
  T* o = out + (img * g.pixels + p) * std::int64_t{g.heads} * d + std::int64_t{a} * d;
  if constexpr (kPacked) {
#pragma unroll
    for (int i0 = 0; i0 < kMaxDim; i0 += detail::kPack) {
      if (i0 >= d) break;
      float v[detail::kPack];
#pragma unroll
      for (int e = 0; e < detail::kPack; ++e) v[e] = dot(i0 + e) / den;
      detail::store8(o + i0, v);
    }
  } else {
    for (int i = 0; i < d; ++i) o[i] = detail::from_f32<T>(dot(i) / den);
  }
}

// Quadratic order, one warp per (pixel n, head, image): S(m, n) = relu(k_m)·relu(q_n),
// out_i(n) = Σ_m v_i(m) S(m, n) / (Σ_m S(m, n) + eps).
template <class T>
__global__ void quadratic_kernel(const T* __restrict__ qkv, T* __restrict__ out, Geometry g, float eps) {
  const int d = g.d, a = blockIdx.y, lane = threadIdx.x & 31, warps = blockDim.x >> 5;
  const std::int64_t img = blockIdx.z;
  const T* base = qkv + img * g.pixels * g.row() + 3 * std::int64_t{a} * d;
  T* obase = out + img * g.pixels * std::int64_t{g.heads} * d + std::int64_t{a} * d;
  for (std::int64_t n = blockIdx.x * std::int64_t{warps} + (threadIdx.x >> 5); n < g.pixels;
       n += std::int64_t{gridDim.x} * warps) {
    const float q = lane < d ? relu(detail::to_f32(base[n * g.row() + lane])) : 0.f;
    float num = 0.f, den = 0.f;
    for (std::int64_t m = 0; m < g.pixels; ++m) {
      const T* px = base + m * g.row();
      const float k = lane < d ? relu(detail::to_f32(px[d + lane])) : 0.f;
      const float s = detail::warp_sum(k * q);
      if (lane < d) num += detail::to_f32(px[2 * d + lane]) * s;
      den += s;
    }
    if (lane < d) obase[n * g.heads * d + lane] = detail::from_f32<T>(num / (den + eps));
  }
}

inline dim3 grid(std::int64_t x, std::int64_t heads, std::int64_t images) {
  return dim3(static_cast<unsigned>(x), static_cast<unsigned>(heads), static_cast<unsigned>(images));
}

}  // namespace mla_detail

// LiteMLA's ReLU linear attention over channels-last maps: qkv (N, HW, heads·3·d), per head a
// q in channels [3da, 3da+d), k in [3da+d, 3da+2d), v in [3da+2d, 3da+3d); out (N, HW, heads·d),
// head a in channels [da, da+d). q and k pass through ReLU as they are read (qkv is not
// modified). Order as cpu::relu_linear_attention (Auto: linear when HW > d). d <= 32.
template <class T>
void relu_linear_attention(Context& ctx, const T* qkv, T* out, std::int64_t N, std::int64_t heads, std::int64_t d,
                           std::int64_t HW, float eps, AttentionOrder order = AttentionOrder::Auto) {
  using namespace mla_detail;
  static_assert(is_device_float<T>, "relu_linear_attention takes float or bf16");
  EPONA_CHECK(N >= 0 && heads > 0 && HW >= 0 && d > 0, "relu_linear_attention: bad extents (N ", N, ", heads ",
              heads, ", d ", d, ", HW ", HW, ")");
  EPONA_CHECK(d <= kMaxDim, "relu_linear_attention: head dim ", d, " > ", kMaxDim, " is not supported on the GPU");
  EPONA_CHECK(N <= 65535 && heads <= 65535, "relu_linear_attention: ", N, " images x ", heads,
              " heads exceed one launch");
  EPONA_CHECK(qkv && out, "relu_linear_attention: null input or output");
  if (N == 0 || HW == 0) return;
  const Geometry g{HW, static_cast<int>(heads), static_cast<int>(d)};
  const bool linear = order == AttentionOrder::Auto ? HW > d : order == AttentionOrder::Linear;
  if (!linear) {
    constexpr int warps = kThreads / 32, pixels_per_warp = 16;  // amortise each block's start
    const std::int64_t pixel_blocks =
        std::min<std::int64_t>((HW + warps * pixels_per_warp - 1) / (warps * pixels_per_warp), 65535);
    quadratic_kernel<<<grid(pixel_blocks, heads, N), kThreads, 0, ctx.stream()>>>(qkv, out, g, eps);
    EPONA_CUDA_CHECK_LAUNCH();
    return;
  }
  EPONA_CHECK((HW + kThreads - 1) / kThreads <= 0x7fffffff, "relu_linear_attention: ", HW, " pixels exceed one launch");
  // Enough chunks for about four blocks per multiprocessor (short serial tile loops), each of at
  // least one tile.
  const std::int64_t want = std::max<std::int64_t>(1, 4 * ctx.info().multiprocessors / (N * heads));
  const std::int64_t chunks = std::clamp<std::int64_t>(std::min(want, (HW + kTile - 1) / kTile), 1, 1024);
  const std::int64_t chunk_pixels = (HW + chunks - 1) / chunks;
  const int entries = static_cast<int>((d + 1) * d);
  Tensor<float, Cuda> partial = scratch_tensor<float>(ctx, {N * heads * chunks * entries});
  Tensor<float, Cuda> m = scratch_tensor<float>(ctx, {N * heads * entries});
  // 16-byte loads and stores when every head's row segment is 16-byte aligned
  const bool packed = d % detail::kPack == 0 && detail::aligned16(qkv) && detail::aligned16(out);
  const auto launch = [&](auto packed_tag) {
    constexpr bool kPacked = decltype(packed_tag)::value;
    partial_kernel<T, kPacked><<<grid(chunks, heads, N), kThreads, 0, ctx.stream()>>>(qkv, partial.data(), g,
                                                                                      chunk_pixels);
    EPONA_CUDA_CHECK_LAUNCH();
    reduce_kernel<><<<detail::grid_for(N * heads * entries, kThreads), kThreads, 0, ctx.stream()>>>(
        partial.data(), m.data(), N * heads, static_cast<int>(chunks), entries);
    EPONA_CUDA_CHECK_LAUNCH();
    apply_kernel<T, kPacked><<<grid((HW + kThreads - 1) / kThreads, heads, N), kThreads, 0, ctx.stream()>>>(
        qkv, m.data(), out, g, eps);
    EPONA_CUDA_CHECK_LAUNCH();
  };
  if (packed) launch(std::true_type{});
  else launch(std::false_type{});
}

}  // namespace epona::cuda
