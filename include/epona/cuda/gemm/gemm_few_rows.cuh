// epona/cuda/gemm/gemm_few_rows.cuh — our own Hopper (sm_90a) bf16 GEMM for products of a few hundred
// rows, y = act(x · wᵀ + b), that can start behind a programmatic edge. The DiTs' condition
// streams (515 rows in the TrajDiT, 530 in the VisDiT's single blocks) are chains of such
// products inside the samplers' graphs; cuBLASLt's kernels never execute griddepcontrol.wait, so
// each of them starts only when the kernel before has drained (docs/gpu-log.md "Session 20").
// Here the producer thread loads the weight halves of the first stages before
// griddepcontrol.wait (weights are model parameters: no kernel before writes them) and x after.
//
// One output tile (64 or 128 rows x 128 or 256 columns) per CTA; a producer warp streams
// 64-deep slices of x and w by TMA (128-byte swizzle, out-of-range rows and depth zero-filled);
// one consumer warpgroup per 64 rows multiplies with wgmma into float32 registers. A deep
// product may split its depth over a cluster of 2 or 4 CTAs: each parks its partial tile in its
// shared memory, and rank r sums rows r/S of the tile over the ranks in rank order through
// distributed shared memory (deterministic, and no global workspace that concurrent streams
// would have to share).
//
// Numerics: float32 sum + bias, then the activation in float32, rounded to bf16 once (what
// cuBLASLt's fused bias / tanh-GELU epilogue stores).
//
// EPONA_CUDA_FEW_ROWS_GEMM=1 sends cuda::linear's bf16 products of 64-2048 rows without an
// activation or with the tanh GELU here. Off by default: on the H100 it is 1.5-2.5x slower than
// cuBLASLt at the DiTs' shapes (cuBLASLt multicasts each weight tile to a 4-CTA cluster), which
// the programmatic launch (0.9-3.4 us per product) does not make up; docs/gpu-log.md
// "Session 22". A base for a multicast version. With it on,
// linear assumes its w is not written by the kernel just before it in the stream (true of
// every product in the models, whose w are parameters; not of a w a caller has just computed).
#pragma once

#include <cuda.h>

#include <algorithm>
#include <atomic>
#include <cstdint>

#include "epona/core/env.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/cuda/pointwise/activation.cuh"
#include "epona/cuda/runtime/cluster.cuh"
#include "epona/cuda/gemm/gemm_wgmma.cuh"

namespace epona::cuda::detail {

namespace fr {

constexpr int kDepth = hg::kDepth;  // channels of a stage's slice: one 128-byte swizzled row

// A tile shape: BM x BN outputs per CTA, the depth split over Splits CTAs of a cluster.
template <int BM, int BN, int Splits>
struct TileShape {
  static_assert(BM == 64 || BM == 128, "a consumer warpgroup per 64 rows");
  static_assert(BN == 128 || BN == 256, "wgmma n128 / n256");
  static_assert(Splits == 1 || Splits == 2 || Splits == 4, "the cluster's ranks split the rows evenly");
  static constexpr int rows = BM, cols = BN, splits = Splits;
  static constexpr int consumers = BM / 64;
  static constexpr int threads = 128 * consumers + 32;  // consumer warpgroups, then the producer warp
  static constexpr int x_bytes = BM * kRowBytes, w_bytes = BN * kRowBytes, stage_bytes = x_bytes + w_bytes;
  // Small tiles keep two CTAs per multiprocessor (at most ~113 KiB each), large ones one.
  static constexpr int budget = BM * BN <= 64 * 128 ? 104 * 1024 : 212 * 1024;
  static constexpr int stages = std::min(8, budget / stage_bytes);
  static constexpr int partial_ld = BN + 8;  // floats: 32 bytes of padding keep the float2 writes conflict-free
  static constexpr int partial_bytes = Splits > 1 ? BM * partial_ld * 4 : 0;
  static constexpr int bars_offset = std::max(stages * stage_bytes, partial_bytes);
  static constexpr int smem_bytes = bars_offset + 16 * stages + kAtomBytes;  // + slack for first_atom
  static_assert(stages >= 2, "double buffering at least");
};

// Where a CTA's stages and barriers lie in its shared memory (from the first atom `base`).
template <class S>
struct StageLayout {
  unsigned base;
  __device__ unsigned x(int st) const { return base + st * S::stage_bytes; }
  __device__ unsigned w(int st) const { return x(st) + S::x_bytes; }
  __device__ unsigned full(int st) const { return base + S::bars_offset + 8 * st; }              // TMA -> consumers
  __device__ unsigned empty(int st) const { return base + S::bars_offset + 8 * (S::stages + st); }  // consumers -> TMA
};

struct Args {
  const bf16* bias;  // (N) or null
  bf16* y;           // rows ldy apart
  int M, N, K, ldy, row_tiles;
  bool early_weights;  // load the first stages' weights before griddepcontrol.wait
};

// The epilogue of outputs col and col + 1: Op(sum + bias) in float32, the pair rounded once to
// two bf16 in one word (low: col).
template <class Op>
__device__ __forceinline__ unsigned finish_pair(const Op& op, float lo, float hi, const bf16* bias, int col) {
  if (bias) lo += to_f32(bias[col]), hi += to_f32(bias[col + 1]);
  return hg::RoundedThen<Identity>::round_pair(op(lo), op(hi));
}

// A consumer warp's 16 rows x BN columns (accumulator layout: rows r, r + 8; columns 8 i + c,
// + 1) straight to y, bounds-checked (N even: a pair is in or out as a whole).
template <int BN, class Op>
__device__ __forceinline__ void store_rows(const float (&acc)[BN / 8][4], const Args& g, const Op& op, int m, int n0,
                                           int c) {
#pragma unroll
  for (int h = 0; h < 2; ++h) {
    const int row = m + 8 * h;
    if (row >= g.M) continue;
#pragma unroll
    for (int i = 0; i < BN / 8; ++i) {
      const int col = n0 + 8 * i + c;
      if (col >= g.N) continue;
      *reinterpret_cast<unsigned*>(g.y + static_cast<std::int64_t>(row) * g.ldy + col) =
          finish_pair(op, acc[i][2 * h], acc[i][2 * h + 1], g.bias, col);
    }
  }
}

// The same rows as float32 pairs into this CTA's partial tile (row-major, ld floats).
template <int BN>
__device__ __forceinline__ void park_rows(const float (&acc)[BN / 8][4], float* partial, int ld, int r, int c) {
#pragma unroll
  for (int h = 0; h < 2; ++h)
#pragma unroll
    for (int i = 0; i < BN / 8; ++i)
      *reinterpret_cast<float2*>(partial + (r + 8 * h) * ld + 8 * i + c) =
          make_float2(acc[i][2 * h], acc[i][2 * h + 1]);
}

// Rank `rank`'s share of the split tile: its BM / S rows, summed over the cluster's partial
// tiles in rank order, finished and stored, four columns per step (N % 4 == 0).
template <class S, class Op>
__device__ __forceinline__ void combine_rows(float* partial, const Args& g, const Op& op, int m0, int n0, int rank) {
  constexpr int rows = S::rows / S::splits, quads = S::cols / 4;
  for (int q = threadIdx.x; q < rows * quads; q += S::threads) {
    const int row = rank * rows + q / quads, col = 4 * (q % quads);
    const int gm = m0 + row, gn = n0 + col;
    if (gm >= g.M || gn >= g.N) continue;
    float4 sum = *reinterpret_cast<const float4*>(cluster_peer(partial, 0) + row * S::partial_ld + col);
#pragma unroll
    for (int s = 1; s < S::splits; ++s) {
      const float4 p = *reinterpret_cast<const float4*>(cluster_peer(partial, s) + row * S::partial_ld + col);
      sum.x += p.x, sum.y += p.y, sum.z += p.z, sum.w += p.w;
    }
    *reinterpret_cast<uint2*>(g.y + static_cast<std::int64_t>(gm) * g.ldy + gn) =
        make_uint2(finish_pair(op, sum.x, sum.y, g.bias, gn), finish_pair(op, sum.z, sum.w, g.bias, gn + 2));
  }
}

// The producer thread: the weight slices of the first stages before griddepcontrol.wait (the
// kernel before may still run: w must not be its output), x after; then the ring of stages.
template <class S>
__device__ __forceinline__ void produce(const CUtensorMap& x_map, const CUtensorMap& w_map, StageLayout<S> at, int m0,
                                        int n0, int k_begin, int slices, bool early_weights) {
  const int early = !early_weights ? 0 : slices < S::stages ? slices : S::stages;
  for (int i = 0; i < early; ++i) {
    mbar::expect_bytes(at.full(i), S::stage_bytes);
    tma_load_2d(at.w(i), w_map, (k_begin + i) * kDepth, n0, at.full(i));
  }
  wait_for_producer();
  for (int i = 0; i < early; ++i) tma_load_2d(at.x(i), x_map, (k_begin + i) * kDepth, m0, at.full(i));
  for (int i = early; i < slices; ++i) {
    const int st = i % S::stages;
    mbar::wait(at.empty(st), (i / S::stages + 1) & 1);  // the slice S::stages earlier was consumed
    mbar::expect_bytes(at.full(st), S::stage_bytes);
    tma_load_2d(at.x(st), x_map, (k_begin + i) * kDepth, m0, at.full(st));
    tma_load_2d(at.w(st), w_map, (k_begin + i) * kDepth, n0, at.full(st));
  }
}

// Consumer warpgroup c: rows 64 c .. + 64 of the tile by all BN columns over this CTA's slices.
template <class S>
__device__ __forceinline__ void consume(float (&acc)[S::cols / 8][4], StageLayout<S> at, int c, int slices) {
#pragma unroll
  for (int i = 0; i < S::cols / 8; ++i) acc[i][0] = acc[i][1] = acc[i][2] = acc[i][3] = 0.f;
  for (int i = 0; i < slices; ++i) {
    const int st = i % S::stages;
    mbar::wait(at.full(st), (i / S::stages) & 1);
    wgmma_fence();
#pragma unroll
    for (int k = 0; k < kDepth / 16; ++k)  // 16 channels = 32 bytes along the swizzled rows
      wgmma_ss(acc, smem_desc(at.x(st) + c * 64 * kRowBytes + 32 * k, 16, kAtomBytes),
               smem_desc(at.w(st) + 32 * k, 16, kAtomBytes), 1);
    wgmma_commit();
    wgmma_wait<1>();  // the previous slice's products are done: release its stage
    if (i > 0 && threadIdx.x % 32 == 0) mbar::arrive(at.empty((i - 1) % S::stages));
  }
  wgmma_wait<0>();
  pin(acc);
}

template <class S, class Op>
__global__ void __launch_bounds__(S::threads)
    few_rows_kernel(const __grid_constant__ CUtensorMap x_map, const __grid_constant__ CUtensorMap w_map, const Args g,
                    Op op) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  extern __shared__ __align__(16) unsigned char smem[];
  const StageLayout<S> at{first_atom(smem)};
  float* const partial = reinterpret_cast<float*>(smem + (at.base - smem_addr(smem)));  // split tiles: over the stages
  const int tile = blockIdx.x / S::splits, rank = blockIdx.x % S::splits;  // 1-D clusters of S::splits
  const int m0 = tile % g.row_tiles * S::rows, n0 = tile / g.row_tiles * S::cols;
  const int k_tiles = (g.K + kDepth - 1) / kDepth;
  const int k_begin = rank * k_tiles / S::splits, slices = (rank + 1) * k_tiles / S::splits - k_begin;
  if (threadIdx.x == 0) {
    for (int st = 0; st < S::stages; ++st) {
      mbar::init(at.full(st), 1);
      mbar::init(at.empty(st), 4 * S::consumers);  // lane 0 of each consumer warp
    }
    asm volatile("fence.mbarrier_init.release.cluster;\n" ::: "memory");
  }
  __syncthreads();
  const int consumer_threads = 128 * S::consumers;
  float acc[S::cols / 8][4];
  if (threadIdx.x == consumer_threads) {
    produce<S>(x_map, w_map, at, m0, n0, k_begin, slices, g.early_weights);
  } else if (threadIdx.x < consumer_threads) {
    wait_for_producer();  // y may be read by the kernel before (its results reach here only through x anyway)
    const int c = threadIdx.x / 128, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32;
    consume<S>(acc, at, c, slices);
    const int r = 64 * c + 16 * warp + lane / 4;
    if constexpr (S::splits == 1) {
      store_rows<S::cols>(acc, g, op, m0 + r, n0, 2 * (lane % 4));
    } else {
      named_barrier(1, consumer_threads);  // the other warpgroup's wgmma no longer read the stages
      park_rows<S::cols>(acc, partial, S::partial_ld, r, 2 * (lane % 4));
    }
  }
  if constexpr (S::splits > 1) {
    __syncwarp();  // the producer warp reconverges (its lane 0 ran produce)
    cluster_sync();  // every rank's partial tile is parked
    combine_rows<S>(partial, g, op, m0, n0, rank);
    cluster_sync();  // no rank leaves (freeing its shared memory) while another still reads it
  }
#else
  (void)g, (void)op;
#endif
}

// The tiles a product can take (the first three whole depth, the last two split over a cluster).
enum class Choice { k64x128, k128x128, k64x256, k64x128k2, k64x128k4 };
constexpr int kChoices = 5;

// Calls f(TileShape{}) for the shape of `choice`.
template <class F>
decltype(auto) with_shape(Choice choice, F&& f) {
  switch (choice) {
    case Choice::k64x128: return f(TileShape<64, 128, 1>{});
    case Choice::k128x128: return f(TileShape<128, 128, 1>{});
    case Choice::k64x256: return f(TileShape<64, 256, 1>{});
    case Choice::k64x128k2: return f(TileShape<64, 128, 2>{});
    default: return f(TileShape<64, 128, 4>{});
  }
}

// A latency estimate (µs) of a product under `choice`, for choose(): a wave of CTAs streams its
// slices at the slower of the tensor cores (~7.5 TFLOP/s per multiprocessor) and the L2 feed
// (~110 B/ns per multiprocessor); CTAs sharing a multiprocessor share both; a launch and
// prologue cost ~2 µs, the cluster's exchange ~0.5 µs per rank. Crude: on the H100 it picked
// the fastest tile for 6 of the 9 DiT shapes, within 6 % on two more, 24 % off on the VisDiT's
// fc2 (bench_cuda_small_kernels --only few_rows).
inline double estimate_us(Choice choice, std::int64_t M, std::int64_t N, std::int64_t K, int multiprocessors) {
  return with_shape(choice, [&](auto s) {
    using S = decltype(s);
    const std::int64_t ctas = (M + S::rows - 1) / S::rows * ((N + S::cols - 1) / S::cols) * S::splits;
    const int per_sm = S::rows * S::cols <= 64 * 128 ? 2 : 1;
    const std::int64_t sharing = std::min<std::int64_t>(per_sm, (ctas + multiprocessors - 1) / multiprocessors);
    const std::int64_t slots = std::int64_t{multiprocessors} * per_sm, waves = (ctas + slots - 1) / slots;
    const double slices = double((K + kDepth - 1) / kDepth) / S::splits;
    const double slice_us = std::max(2.0 * S::rows * S::cols * kDepth / 7.5e6, double(S::stage_bytes) / 1.1e5);
    return 2.0 + 0.5 * (S::splits - 1) + double(waves * sharing) * slices * slice_us;
  });
}

inline Choice choose(std::int64_t M, std::int64_t N, std::int64_t K, int multiprocessors) {
  Choice best = Choice::k64x128;
  for (int i = 1; i < kChoices; ++i)
    if (estimate_us(Choice(i), M, N, K, multiprocessors) < estimate_us(best, M, N, K, multiprocessors))
      best = Choice(i);
  return best;
}

}  // namespace fr

// EPONA_CUDA_FEW_ROWS_GEMM=1 routes linear's bf16 products of 64-2048 rows (no activation or
// the tanh GELU) to few_rows_gemm; off by default (measured slower than cuBLASLt, see the top).

// Where linear tries it (few_rows_gemm itself declines the epilogues it lacks).
inline bool few_rows_wins(const Context& ctx, std::int64_t M, std::int64_t K) {
  return ctx.policy().few_rows_gemm && M >= 64 && M <= 2048 && K >= fr::kDepth;
}

// y = act(x · wᵀ + bias) by the kernel above, as a programmatic launch. early_weights: w's
// first stages are loaded before the wait, so w must not be written by the kernel before in
// the stream (model parameters); false loads everything after it. choice < 0: choose()'s
// pick, else the fr::Choice of that index. false (nothing launched) where the product does not
// fit (own_gemm_fits, N % 8 == 0), the activation is not None / GeluTanh, or the driver cannot
// describe the operands.
inline bool few_rows_gemm(Context& ctx, const bf16* x, std::int64_t ldx, const bf16* w, const bf16* bias, bf16* y,
                          std::int64_t ldy, std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi,
                          int choice = -1, bool early_weights = true) {
  if (N % 8 != 0 || choice >= fr::kChoices || (epi != Epilogue::None && epi != Epilogue::GeluTanh) ||
      !own_gemm_fits(ctx, x, ldx, w, bias, y, ldy, M, N, K) || !clusters_available(ctx))
    return false;
  const fr::Choice pick = choice < 0 ? fr::choose(M, N, K, ctx.info().multiprocessors) : fr::Choice(choice);
  return fr::with_shape(pick, [&](auto s) {
    using S = decltype(s);
    CUtensorMap x_map, w_map;
    if (!hg::matrix_tensor_map(x_map, x, M, K, ldx, S::rows) || !hg::matrix_tensor_map(w_map, w, N, K, K, S::cols))
      return false;
    const int row_tiles = static_cast<int>((M + S::rows - 1) / S::rows);
    const std::int64_t ctas = std::int64_t{row_tiles} * ((N + S::cols - 1) / S::cols) * S::splits;
    const fr::Args g{bias, y, static_cast<int>(M), static_cast<int>(N), static_cast<int>(K), static_cast<int>(ldy),
                     row_tiles, early_weights};
    if (ctas >= std::int64_t{1} << 31 || ldy >= std::int64_t{1} << 31) return false;  // 32-bit grid and rows
    const auto launch = [&](auto op) {
      allow_dynamic_smem<fr::few_rows_kernel<S, decltype(op)>>(S::smem_bytes);
      launch_in_clusters(fr::few_rows_kernel<S, decltype(op)>, dim3(static_cast<unsigned>(ctas)), S::splits, S::threads,
                         S::smem_bytes, ctx, x_map, w_map, g, op);
    };
    if (epi == Epilogue::GeluTanh) launch(GeluTanhOp{});
    else launch(Identity{});
    return true;
  });
}

}  // namespace epona::cuda::detail
