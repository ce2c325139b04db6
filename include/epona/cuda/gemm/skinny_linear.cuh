// epona/cuda/gemm/skinny_linear.cuh — y = act(x · Wᵀ + b) for at most 16 rows of x (the TrajDiT's 15
// trajectory tokens, batch-1 vectors): a weight-bandwidth problem that cuBLASLt runs as 64x8
// tiles, often split-K with a separate reduce kernel. Here a cluster of CTAs owns a band of 32
// output columns and splits K among its warps; each weight element is fetched once (16-byte
// asynchronous copies, a round of them in flight per warp) and the partial sums meet in
// distributed shared memory; bias and the tanh GELU are applied in float32 and rounded once
// (cuBLASLt's fused epilogue). bf16 on tensor cores (mma m16n8k16, rows padded to 16 with
// zeros); float32 with FMA (true float32 arithmetic). Used where it beats cuBLASLt (skinny_wins).
#pragma once

#include <algorithm>
#include <cstdint>
#include <type_traits>

#include "epona/core/env.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/cuda/pointwise/activation.cuh"  // GeluTanhOp: the same function as the other GEMM epilogues
#include "epona/cuda/runtime/cluster.cuh"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/ptx/mma.cuh"

namespace epona::cuda {

namespace detail {

constexpr int kSkinnyRows = 16;                  // rows of x one launch takes (the mma's M)
constexpr int kSkinnyBand = 32;                  // output columns per cluster: 4 tiles of 8
constexpr int kSkinnyTiles = kSkinnyBand / 8;
constexpr int kSkinnyWarps = 8, kSkinnyThreads = 32 * kSkinnyWarps;
// k-chunks whose loads a warp issues together: the measured best where the kernel is used
// (skinny_wins; bf16 1 of 1, 2, 4; float32 2, the only one timed: 15 x 1024 x 5120 47.8 ->
// 39.4 us against cuBLASLt).
template <class T> constexpr int kSkinnyUnroll = std::is_same_v<T, float> ? 2 : 1;
constexpr int kSkinnyMaxSplit = 8;               // CTAs per cluster (the portable limit)

// KernelPolicy::skinny_linear off (EPONA_CUDA_SKINNY=0) sends these products back to cuBLASLt.

// The operands of one product y = act(x · wᵀ + bias) (the small kernels' argument).
template <class T>
struct LinearArgs {
  const T* x;
  std::int64_t ldx;
  const T* w;  // (N, K), rows K apart
  const T* bias;  // or null
  T* y;
  std::int64_t ldy;
  int M, N, K;
};

// Each lane (g = lane / 4, q = lane % 4) loads, per k-chunk of 4·E elements, E = 16 bytes of
// weight row 8t + g (tile t) from k = chunk + q·E. The engines multiply those by x.
template <class T> constexpr int kSkinnyElems = 16 / static_cast<int>(sizeof(T));
template <class T> constexpr int kSkinnyChunk = 4 * kSkinnyElems<T>;

__device__ __forceinline__ uint4 load16(const void* p) { return __ldg(reinterpret_cast<const uint4*>(p)); }

// Weights come by asynchronous copies (mma.cuh) because with register loads ptxas kept 67-78
// registers whatever the unroll, i.e. not a round's loads in flight; the copies of a round are
// all issued before the first wait.
__device__ __forceinline__ void wait_async_copies() {
  cp_async_commit();
  cp_async_wait_all();
}

// How a warp multiplies its k-chunks by x, per storage type; Unroll chunks' loads in flight.
template <class T, int Unroll> struct SkinnyEngine;

// bf16: two m16n8k16 per chunk and tile. k inside a chunk is permuted (the sum does not care):
// lane q's 8 consecutive elements serve as k {2q, 2q+1, 2q+8, 2q+9} of the first mma and of
// the second, for x and weights alike, so both come in one 16-byte load. x rows g and g + 8
// are the A fragment's rows (zero past M).
template <int Unroll>
struct SkinnyEngine<bf16, Unroll> {
  static constexpr int kXSlots = 2;  // x rows g and g + 8, staged beside the weights
  float acc[kSkinnyTiles][4] = {};

  __device__ void prefetch(const LinearArgs<bf16>& a, uint4* x_slots, std::int64_t k, bool ok, int g) {
    cp_async_16_or_zero(x_slots, a.x + g * a.ldx + k, ok && g < a.M, a.x);
    cp_async_16_or_zero(x_slots + 32, a.x + (g + 8) * a.ldx + k, ok && g + 8 < a.M, a.x);
  }
  __device__ void step(const LinearArgs<bf16>&, const uint4* x_slots, std::int64_t, bool, const uint4 (&wv)[kSkinnyTiles]) {
    const uint4 lo = x_slots[0], hi = x_slots[32];
    const unsigned first[4] = {lo.x, hi.x, lo.y, hi.y}, second[4] = {lo.z, hi.z, lo.w, hi.w};
#pragma unroll
    for (int t = 0; t < kSkinnyTiles; ++t) {
      mma_bf16(acc[t], first, wv[t].x, wv[t].y);
      mma_bf16(acc[t], second, wv[t].z, wv[t].w);
    }
  }
  // Accumulator (row g or g + 8, columns 8t + 2q, + 1) into the warp's (16, 32) partial tile.
  __device__ void store(float (*part)[kSkinnyBand], int g, int q) const {
#pragma unroll
    for (int t = 0; t < kSkinnyTiles; ++t) {
      *reinterpret_cast<float2*>(&part[g][8 * t + 2 * q]) = make_float2(acc[t][0], acc[t][1]);
      *reinterpret_cast<float2*>(&part[g + 8][8 * t + 2 * q]) = make_float2(acc[t][2], acc[t][3]);
    }
  }
};

// float32: FMA, each lane summing its 4 elements of k per chunk for every row and its 4
// columns; the 4 lanes of a column group are added at the end.
template <int Unroll>
struct SkinnyEngine<float, Unroll> {
  static constexpr int kXSlots = 0;  // x is read in step, through L1 (8 lanes share each load)
  float acc[kSkinnyRows][kSkinnyTiles] = {};

  __device__ void prefetch(const LinearArgs<float>&, uint4*, std::int64_t, bool, int) {}
  __device__ void step(const LinearArgs<float>& a, const uint4*, std::int64_t k, bool ok, const uint4 (&wv)[kSkinnyTiles]) {
    if (!ok) return;
#pragma unroll
    for (int m = 0; m < kSkinnyRows; ++m) {
      if (m >= a.M) break;
      const uint4 xr = load16(a.x + m * a.ldx + k);
      const float xs[4] = {__uint_as_float(xr.x), __uint_as_float(xr.y), __uint_as_float(xr.z), __uint_as_float(xr.w)};
#pragma unroll
      for (int t = 0; t < kSkinnyTiles; ++t) {
        const float ws[4] = {__uint_as_float(wv[t].x), __uint_as_float(wv[t].y), __uint_as_float(wv[t].z),
                             __uint_as_float(wv[t].w)};
#pragma unroll
        for (int i = 0; i < 4; ++i) acc[m][t] = fmaf(xs[i], ws[i], acc[m][t]);
      }
    }
  }
  __device__ void store(float (*part)[kSkinnyBand], int g, int q) {
#pragma unroll
    for (int m = 0; m < kSkinnyRows; ++m)
#pragma unroll
      for (int t = 0; t < kSkinnyTiles; ++t) {
        float v = acc[m][t];
        v += __shfl_xor_sync(0xffffffffu, v, 1);
        v += __shfl_xor_sync(0xffffffffu, v, 2);
        if ((m & 3) == q) part[m][8 * t + g] = v;
      }
  }
};

// This warp's share of the chunks: the cluster's CTAs (blockIdx.x) and their warps split the
// K/chunk chunks into contiguous, near-equal runs.
struct ChunkRun {
  std::int64_t begin, end;
};
__device__ __forceinline__ ChunkRun warp_chunks(std::int64_t chunks, int split, int warp) {
  const std::int64_t slots = std::int64_t{split} * kSkinnyWarps, slot = std::int64_t{blockIdx.x} * kSkinnyWarps + warp;
  return {chunks * slot / slots, chunks * (slot + 1) / slots};
}

// Sums the cluster's partial tiles for this CTA's share of the band's outputs, adds the bias,
// applies the activation and stores. Each CTA first adds its warps' tiles into tile 0 (local,
// fixed order); then a rank reads the `split` CTA totals of an output with all remote loads
// issued together (one distributed-shared-memory latency, not one per rank and warp).
template <class T, bool Gelu>
__device__ void skinny_finish(const LinearArgs<T>& a, float (*part)[kSkinnyRows][kSkinnyBand], int split) {
  constexpr int kTile = kSkinnyRows * kSkinnyBand;
  __syncthreads();  // the warps' tiles written
  for (int e = threadIdx.x; e < kTile; e += kSkinnyThreads) {
    float sum = part[0][0][e];
#pragma unroll
    for (int w = 1; w < kSkinnyWarps; ++w) sum += part[w][0][e];
    part[0][0][e] = sum;
  }
  cluster_sync();  // every rank's total written
#if EPONA_CUDA_CLUSTERS
  const int n0 = blockIdx.y * kSkinnyBand;
  for (int e = static_cast<int>(__clusterRelativeBlockRank()) * kSkinnyThreads + threadIdx.x; e < a.M * kSkinnyBand;
       e += split * kSkinnyThreads) {
    const int m = e / kSkinnyBand, col = e % kSkinnyBand, n = n0 + col;
    if (n >= a.N) continue;
    float ranks[kSkinnyMaxSplit];
#pragma unroll
    for (int r = 0; r < kSkinnyMaxSplit; ++r)
      ranks[r] = r < split ? static_cast<const float*>(__cluster_map_shared_rank(part, static_cast<unsigned>(r)))[e] : 0.f;
    float sum = ranks[0];
#pragma unroll
    for (int r = 1; r < kSkinnyMaxSplit; ++r)
      if (r < split) sum += ranks[r];
    if (a.bias) sum += to_f32(a.bias[n]);
    if constexpr (Gelu) sum = GeluTanhOp{}(sum);
    a.y[m * a.ldy + n] = from_f32<T>(sum);
  }
#else
  (void)a, (void)split;
  __trap();  // unreachable: no cluster launch on a pre-sm_90 build
#endif
  cluster_sync();  // no rank leaves (freeing its shared memory) while another still reads it
}

// Shared memory of one CTA: per warp and chunk of a round, the lanes' 16-byte slots (weight
// tiles, then the engine's x slots), then the warps' (16, 32) float32 partial tiles.
template <class T, int Unroll>
constexpr int kSkinnySlots = kSkinnyTiles + SkinnyEngine<T, Unroll>::kXSlots;
template <class T, int Unroll>
constexpr int skinny_smem_bytes() {
  return kSkinnyWarps * (Unroll * kSkinnySlots<T, Unroll> * 32 * 16 + kSkinnyRows * kSkinnyBand * 4);
}

// Grid (split, bands), clusters of (split, 1, 1): cluster y owns columns [32y, 32y + 32).
template <class T, bool Gelu, int Unroll>
__global__ void __launch_bounds__(kSkinnyThreads) skinny_linear_kernel(LinearArgs<T> a, int split) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  extern __shared__ uint4 skinny_smem[];
  constexpr int S = kSkinnySlots<T, Unroll>, E = kSkinnyElems<T>, C = kSkinnyChunk<T>;
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, g = lane >> 2, q = lane & 3;
  uint4* stage = skinny_smem + warp * Unroll * S * 32 + lane;  // slot j of chunk u: stage[(u S + j) 32]
  auto* part = reinterpret_cast<float(*)[kSkinnyRows][kSkinnyBand]>(skinny_smem + kSkinnyWarps * Unroll * S * 32);
  const ChunkRun run = warp_chunks((a.K + C - 1) / C, split, warp);
  const T* wrow[kSkinnyTiles];
  bool has_row[kSkinnyTiles];
#pragma unroll
  for (int t = 0; t < kSkinnyTiles; ++t) {
    const int n = blockIdx.y * kSkinnyBand + 8 * t + g;
    has_row[t] = n < a.N;
    wrow[t] = a.w + std::int64_t{has_row[t] ? n : 0} * a.K;
  }
  SkinnyEngine<T, Unroll> engine;
  for (std::int64_t c = run.begin; c < run.end; c += Unroll) {
#pragma unroll
    for (int u = 0; u < Unroll; ++u) {
      const std::int64_t k = (c + u) * C + q * E;
      const bool ok = c + u < run.end && k < a.K;
#pragma unroll
      for (int t = 0; t < kSkinnyTiles; ++t) cp_async_16_or_zero(stage + (u * S + t) * 32, wrow[t] + k, ok && has_row[t], a.w);
      engine.prefetch(a, stage + (u * S + kSkinnyTiles) * 32, k, ok, g);
    }
    wait_async_copies();  // each lane reads back only its own slots: no barrier
#pragma unroll
    for (int u = 0; u < Unroll; ++u) {
      const std::int64_t k = (c + u) * C + q * E;
      uint4 wv[kSkinnyTiles];
#pragma unroll
      for (int t = 0; t < kSkinnyTiles; ++t) wv[t] = stage[(u * S + t) * 32];
      engine.step(a, stage + (u * S + kSkinnyTiles) * 32, k, c + u < run.end && k < a.K, wv);
    }
  }
  engine.store(part[warp], g, q);
  skinny_finish<T, Gelu>(a, part, split);
}

// CTAs per cluster: enough that one round of loads covers each warp's chunks and that the
// clusters fill the SMs, a power of two (cluster shapes), at most 8 and at most a chunk a warp.
inline int skinny_split(int multiprocessors, std::int64_t bands, std::int64_t chunks, int unroll) {
  const auto ceil_div = [](std::int64_t a, std::int64_t b) { return (a + b - 1) / b; };
  const std::int64_t wanted = std::max(ceil_div(chunks, kSkinnyWarps * unroll), ceil_div(multiprocessors, bands));
  const std::int64_t most = std::min<std::int64_t>(kSkinnyMaxSplit, std::max<std::int64_t>(1, chunks / kSkinnyWarps));
  int split = 1;
  while (split < wanted && 2 * split <= most) split *= 2;
  return split;
}

// Where the skinny kernel beats cuBLASLt. Measured on the H200 (bf16, graph of calls on cold
// weights, per call, cuBLASLt -> skinny with 1 / 2 chunks a round): at K >= 4096, where
// cuBLASLt adds a split-K reduce kernel, it wins (15 x 1024 x 4096: 7.28 -> 6.55 / 6.71 us;
// x 5120: 7.75 -> 7.21 / 7.84 us); at K = 1024 it loses (15 x 3072: 4.90 -> 5.67 us, 15 x
// 1024: 4.32 -> 4.47, 15 x 4096 + GELU: 5.12 -> 6.06), and so at every batch-1 vector
// (1 x 6144 x 1024: 5.78 -> 7.11 us; 1 x 12288 x 2048: 15.25 -> 23.7; cuBLASLt's GEMV).
inline bool skinny_wins(std::int64_t M, std::int64_t K) { return M >= 2 && K >= 4096; }

template <class T, bool Gelu, int Unroll>
void launch_skinny(Context& ctx, const LinearArgs<T>& a, int split, std::int64_t bands) {
  constexpr int smem = skinny_smem_bytes<T, Unroll>();
  allow_dynamic_smem<skinny_linear_kernel<T, Gelu, Unroll>>(smem);
  launch_in_clusters(skinny_linear_kernel<T, Gelu, Unroll>, dim3(static_cast<unsigned>(split), static_cast<unsigned>(bands)),
                     static_cast<unsigned>(split), kSkinnyThreads, smem, ctx, a, split);
}

// Runs the product when it is skinny (M <= 16), K a multiple of 8 with 16-byte aligned rows,
// and the epilogue none or the tanh GELU, on a GPU and build with clusters; false (nothing
// launched) otherwise.
// Unroll: chunks per round of loads (benchmarks compare others).
template <class T, int Unroll = kSkinnyUnroll<T>>
bool skinny_linear(Context& ctx, const LinearArgs<T>& a, Epilogue epi) {
  if (!clusters_available(ctx)) return false;
  if (a.M < 1 || a.M > kSkinnyRows || (epi != Epilogue::None && epi != Epilogue::GeluTanh)) return false;
  if (!packable(a.x, a.K, a.ldx) || !packable(a.w, a.K, a.K)) return false;
  const std::int64_t bands = (std::int64_t{a.N} + kSkinnyBand - 1) / kSkinnyBand;
  if (bands > 65535) return false;
  const int split = skinny_split(ctx.info().multiprocessors, bands, (a.K + kSkinnyChunk<T> - 1) / kSkinnyChunk<T>, Unroll);
  if (epi == Epilogue::GeluTanh)
    launch_skinny<T, true, Unroll>(ctx, a, split, bands);
  else
    launch_skinny<T, false, Unroll>(ctx, a, split, bands);
  return true;
}

}  // namespace detail


}  // namespace epona::cuda
