// epona/cuda/lite_mla.cuh — LiteMLA's ReLU linear attention on the GPU over channels-last maps,
// as cpu::relu_linear_attention: per (image, head) the (d+1) x d matrix [v; 1]·relu(k)ᵀ is reduced
// over pixels (per-chunk partial sums, then a fixed-order sum: deterministic), then applied to
// relu(q) per pixel; or the quadratic order for small maps. float32 arithmetic throughout.
#pragma once

#include <algorithm>
#include <cstdint>

#include "epona/cpu/conv.hpp"
#include "epona/cuda/context.hpp"
#include "epona/cuda/device.cuh"
#include "epona/cuda/scratch.hpp"

namespace epona::cuda {

namespace mla_detail {

constexpr int kMaxDim = 32;        // head dims up to one warp
constexpr int kThreads = 256;
constexpr int kTile = 64;          // pixels staged in shared memory per step
constexpr int kEntries = (kMaxDim + 1) * kMaxDim;
constexpr int kPerThread = (kEntries + kThreads - 1) / kThreads;

// Element (pixel p, channel c) of the per-head groups: q at 3·d·a + j, k at +d, v at +2d.
struct Geometry {
  std::int64_t pixels;  // per image
  int heads, d;
  __host__ __device__ std::int64_t row() const { return 3 * std::int64_t{heads} * d; }  // qkv channels per pixel
};

__device__ __forceinline__ float relu(float v) { return v > 0.f ? v : 0.f; }

// grid (chunks, heads, images): partial[(img, head, chunk)][i·d + j] = Σ_p vrow_i(p) relu(k_j(p))
// over the chunk's pixels, with vrow_d = 1 (the ones row: the normaliser's Σ_p relu(k_j(p))).
template <class T>
__global__ void partial_kernel(const T* __restrict__ qkv, float* __restrict__ partial, Geometry g,
                               std::int64_t chunk_pixels) {
  __shared__ float ks[kTile][kMaxDim], vs[kTile][kMaxDim];
  const int d = g.d, a = blockIdx.y, chunk = blockIdx.x, chunks = gridDim.x;
  const std::int64_t img = blockIdx.z;
  const T* base = qkv + img * g.pixels * g.row() + 3 * std::int64_t{a} * d;
  const std::int64_t p_begin = chunk * chunk_pixels, p_end = std::min(g.pixels, p_begin + chunk_pixels);
  float acc[kPerThread] = {};
  for (std::int64_t t0 = p_begin; t0 < p_end; t0 += kTile) {
    const int n = static_cast<int>(std::min<std::int64_t>(kTile, p_end - t0));
    for (int e = threadIdx.x; e < n * d; e += blockDim.x) {
      const int p = e / d, j = e % d;
      const T* px = base + (t0 + p) * g.row();
      ks[p][j] = relu(detail::to_f32(px[d + j]));
      vs[p][j] = detail::to_f32(px[2 * d + j]);
    }
    __syncthreads();
#pragma unroll
    for (int t = 0; t < kPerThread; ++t) {
      const int e = threadIdx.x + t * kThreads;
      if (e >= (d + 1) * d) continue;
      const int i = e / d, j = e % d;
      float s = acc[t];
      for (int p = 0; p < n; ++p) s += (i < d ? vs[p][i] : 1.0f) * ks[p][j];
      acc[t] = s;
    }
    __syncthreads();
  }
  float* out = partial + ((img * gridDim.y + a) * chunks + chunk) * std::int64_t{(d + 1) * d};
#pragma unroll
  for (int t = 0; t < kPerThread; ++t) {
    const int e = threadIdx.x + t * kThreads;
    if (e < (d + 1) * d) out[e] = acc[t];
  }
}

// m[(img, head)][e] = Σ_chunk partial[(img, head, chunk)][e], chunks in order.
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

// grid (pixel blocks, heads, images), one warp per pixel: out_i = Σ_j M[i][j] q_j / (Σ_j M[d][j] q_j + eps).
template <class T>
__global__ void apply_kernel(const T* __restrict__ qkv, const float* __restrict__ m, T* __restrict__ out, Geometry g,
                             float eps) {
  __shared__ float ms[(kMaxDim + 1) * (kMaxDim + 1)];
  const int d = g.d, a = blockIdx.y, lane = threadIdx.x & 31, warps = blockDim.x >> 5;
  const std::int64_t img = blockIdx.z;
  const float* mat = m + (img * gridDim.y + a) * std::int64_t{(d + 1) * d};
  for (int e = threadIdx.x; e < (d + 1) * d; e += blockDim.x) ms[(e / d) * (d + 1) + e % d] = mat[e];
  __syncthreads();
  const T* base = qkv + img * g.pixels * g.row() + 3 * std::int64_t{a} * d;
  T* obase = out + img * g.pixels * std::int64_t{g.heads} * d + std::int64_t{a} * d;
  for (std::int64_t p = blockIdx.x * std::int64_t{warps} + (threadIdx.x >> 5); p < g.pixels;
       p += std::int64_t{gridDim.x} * warps) {
    const float q = lane < d ? relu(detail::to_f32(base[p * g.row() + lane])) : 0.f;
    float num = 0.f, den = 0.f;
    for (int j = 0; j < d; ++j) {
      const float qj = __shfl_sync(0xffffffffu, q, j);
      if (lane < d) num += ms[lane * (d + 1) + j] * qj;
      den += ms[d * (d + 1) + j] * qj;
    }
    if (lane < d) obase[p * g.heads * d + lane] = detail::from_f32<T>(num / (den + eps));
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
                           std::int64_t HW, float eps, cpu::AttentionOrder order = cpu::AttentionOrder::Auto) {
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
  const bool linear = order == cpu::AttentionOrder::Auto ? HW > d : order == cpu::AttentionOrder::Linear;
  constexpr int warps = kThreads / 32, pixels_per_warp = 16;  // amortise each block's load of the matrix
  const std::int64_t pixel_blocks =
      std::min<std::int64_t>((HW + warps * pixels_per_warp - 1) / (warps * pixels_per_warp), 65535);
  if (!linear) {
    quadratic_kernel<<<grid(pixel_blocks, heads, N), kThreads, 0, ctx.stream()>>>(qkv, out, g, eps);
    EPONA_CUDA_CHECK_LAUNCH();
    return;
  }
  // Enough chunks for about two blocks per multiprocessor, each of at least one tile.
  const std::int64_t want = std::max<std::int64_t>(1, 2 * ctx.info().multiprocessors / (N * heads));
  const std::int64_t chunks = std::clamp<std::int64_t>(std::min(want, (HW + kTile - 1) / kTile), 1, 1024);
  const std::int64_t chunk_pixels = (HW + chunks - 1) / chunks;
  const int entries = static_cast<int>((d + 1) * d);
  Tensor<float, Cuda> partial = scratch_tensor<float>(ctx, {N * heads * chunks * entries});
  Tensor<float, Cuda> m = scratch_tensor<float>(ctx, {N * heads * entries});
  partial_kernel<<<grid(chunks, heads, N), kThreads, 0, ctx.stream()>>>(qkv, partial.data(), g, chunk_pixels);
  EPONA_CUDA_CHECK_LAUNCH();
  reduce_kernel<<<detail::grid_for(N * heads * entries, kThreads), kThreads, 0, ctx.stream()>>>(
      partial.data(), m.data(), N * heads, static_cast<int>(chunks), entries);
  EPONA_CUDA_CHECK_LAUNCH();
  apply_kernel<<<grid(pixel_blocks, heads, N), kThreads, 0, ctx.stream()>>>(qkv, m.data(), out, g, eps);
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda
