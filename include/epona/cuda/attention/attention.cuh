// epona/cuda/attention/attention.cuh — fused scaled-dot-product attention on the GPU (flash attention:
// online softmax over key tiles, no score matrix in memory) over strided, token-major data,
// as the CPU's attention(): packed QKV, the MST's frame-strided temporal attention, causal
// and additive masks. bf16 runs on tensor cores (float32 accumulation and softmax): wgmma on
// Hopper in sm_90a builds (attention_wgmma.cuh; head dim 128, no additive mask), mma.sync
// m16n8k16 otherwise, and a warp-per-head kernel for sequences of <= 16, as the MST's 10
// frames; float32 runs a float32 SIMT kernel so it matches the CPU to float32 rounding.
#pragma once

#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>

#include "epona/core/env.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/cuda/attention/attention_common.cuh"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/ptx/mma.cuh"

namespace epona::cuda {
namespace detail {
namespace fa {

template <class Tile, bool kExactDim>
__global__ void __launch_bounds__(Tile::threads, Tile::min_blocks)
    flash_bf16_kernel(const FlashParams<bf16> p, int heads, int seqs) {
  constexpr int kRows = Tile::rows, kKeys = Tile::keys, kM = Tile::m_tiles, kGroups = Tile::groups;
  extern __shared__ __align__(16) unsigned char smem[];
  bf16* sQ = reinterpret_cast<bf16*>(smem);
  bf16* sKV = sQ + kRows * kStride;  // [stage][group] (K, V)

  const BlockCoords block = block_coords(p, heads, seqs, kRows);
  const std::int64_t s = block.s;
  const int h = block.h, q0 = block.q0;

  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  const int group = warp / Tile::warps, warp_in_group = warp % Tile::warps;
  const int D = kExactDim ? kMaxHeadDim : p.head_dim;
  const bf16* kg = p.k + s * p.k_seq + std::int64_t{h} * D;
  const bf16* vg = p.v + s * p.v_seq + std::int64_t{h} * D;
  const int tiles = key_tiles(q0, kRows, p.lq, p.lk, p.causal, kKeys);
  const int steps = (tiles + kGroups - 1) / kGroups;  // step i: tile i kGroups + g for group g
  const auto kv_tile = [&](int step, int g) { return sKV + ((step & 1) * kGroups + g) * Tile::kv_elems; };
  // Each group loads its own tiles with its own threads and waits on its own barrier, so
  // the groups run as independently as separate blocks would.
  constexpr int kGroupThreads = 32 * Tile::warps;
  const int group_thread = threadIdx.x - group * kGroupThreads;
  const auto load_own_tile = [&](int step) {
    const int t = step * kGroups + group;
    if (t >= tiles) return;
    bf16* sK = kv_tile(step, group);
    load_tile<kExactDim>(sK, kg, p.k_row, t * kKeys, kKeys, p.lk, D, group_thread, kGroupThreads);
    load_tile<kExactDim>(sK + kKeys * kStride, vg, p.v_row, t * kKeys, kKeys, p.lk, D, group_thread, kGroupThreads);
  };

  load_tile<kExactDim>(sQ, p.q + s * p.q_seq + std::int64_t{h} * D, p.q_row, q0, kRows, p.lq, D, threadIdx.x,
                       Tile::threads);
  load_own_tile(0);
  cp_async_commit();
  cp_async_wait_all();
  __syncthreads();  // Q (shared by the groups) and every group's first tile landed

  float o[kM][kDimTiles][4] = {};
  float m[kM][2], l[kM][2];
  int rows[kM][2];
  const int row0 = q0 + warp_in_group * kM * 16;  // this warp's first query row
#pragma unroll
  for (int mt = 0; mt < kM; ++mt)
#pragma unroll
    for (int i = 0; i < 2; ++i) {
      m[mt][i] = -INFINITY, l[mt][i] = 0.f;
      rows[mt][i] = row0 + mt * 16 + lane / 4 + 8 * i;
    }
  // A warp whose rows all lie past lq only loads; under a causal mask a warp skips the key
  // tiles that start past its last row (they would add exactly nothing).
  const bool warp_active = row0 < p.lq;
  const int warp_last_row = row0 + kM * 16 - 1;

  for (int i = 0; i < steps; ++i) {
    if (i > 0) {
      cp_async_wait_all();
      // The group's tile i landed; its warps are done with tile i - 1's stage.
      if constexpr (kGroups == 1)
        __syncthreads();
      else
        named_barrier(1 + group, kGroupThreads);
    }
    if (i + 1 < steps) {
      load_own_tile(i + 1);
      cp_async_commit();
    }
    const int t = i * kGroups + group, k0 = t * kKeys;
    if (t < tiles && warp_active && !(p.causal && k0 > warp_last_row)) {
      const bf16* sK = kv_tile(i, group);
      warp_tile<kExactDim, kM, kKeys>(o, m, l, p, sQ + warp_in_group * kM * 16 * kStride, sK, sK + kKeys * kStride,
                                      row0, rows, k0, lane, D);
    }
  }
  if constexpr (kGroups > 1) {
    merge_groups<Tile>(o, m, l, reinterpret_cast<float*>(sKV), group, warp_in_group, lane);
    if (group > 0) return;
  }
#pragma unroll
  for (int mt = 0; mt < kM; ++mt) store_rows<kExactDim>(o[mt], l[mt], p, rows[mt], s, h, D, lane % 4);
}

// Short sequences (lq, lk <= 16: the MST's temporal attention over its 10 frames). One warp
// per (sequence, head) loads Q, K and V once into its own shared memory (no block barrier),
// computes the 16 x 16 scores and P V with 32 mma, and stores. A block of 4 warps takes 4
// consecutive (sequence, head) pairs: the heads of one token are adjacent. The 16-row
// operand tiles overlap, so that a warp needs max(lq + 2 lk + 1, lq + 16) rows rather than 48
// (more warps fit a multiprocessor: 31 rows at the MST's 10 x 10 let 6 blocks share one with the
// QK norm's statistics, against 5 with 16-row V tiles): Q's rows past lq are K's rows (they make
// score rows that are never stored), K's rows past lk are V's and what follows (their scores are
// replaced by -inf), and V's rows past lk are read from a row of zeros after V (P = 0 there;
// 0 times garbage could be NaN).
constexpr int kShortWarps = 4, kShortThreads = 32 * kShortWarps, kShortLen = 16;
__host__ __device__ inline int short_warp_rows(int lq, int lk) {
  return lq + 2 * lk + 1 > lq + kShortLen ? lq + 2 * lk + 1 : lq + kShortLen;
}
__host__ __device__ inline int short_smem_bytes(int lq, int lk) {
  return kShortWarps * short_warp_rows(lq, lk) * kStride * 2;
}

// A warp's overlapping Q, K and V tiles of (sequence s, head h) and its zero row in shared
// memory, their loads issued and committed (the caller waits).
struct ShortTiles {
  bf16 *q, *k, *v, *zero;
};
template <bool kExactDim>
__device__ __forceinline__ ShortTiles load_short_tiles(unsigned char* smem, const FlashParams<bf16>& p,
                                                       std::int64_t s, int h, int warp, int lane, int D) {
  bf16* sQ = reinterpret_cast<bf16*>(smem) + warp * short_warp_rows(p.lq, p.lk) * kStride;
  bf16* sK = sQ + p.lq * kStride;
  bf16* sV = sK + p.lk * kStride;
  bf16* zero = sV + p.lk * kStride;
  load_tile<kExactDim>(sQ, p.q + s * p.q_seq + std::int64_t{h} * D, p.q_row, 0, p.lq, p.lq, D, lane, 32);
  load_tile<kExactDim>(sK, p.k + s * p.k_seq + std::int64_t{h} * D, p.k_row, 0, p.lk, p.lk, D, lane, 32);
  load_tile<kExactDim>(sV, p.v + s * p.v_seq + std::int64_t{h} * D, p.v_row, 0, p.lk, p.lk, D, lane, 32);
  if (lane < kMaxHeadDim / 8) reinterpret_cast<uint4*>(zero)[lane] = make_uint4(0, 0, 0, 0);
  cp_async_commit();
  return {sQ, sK, sV, zero};
}
// The warp's 16 x 16 scores, softmax and P V over its loaded tiles, stored.
template <bool kExactDim>
__device__ __forceinline__ void short_attend(const FlashParams<bf16>& p, const ShortTiles& t, std::int64_t s, int h,
                                             int lane, int D) {
  float o[1][kDimTiles][4] = {};
  float m[1][2] = {{-INFINITY, -INFINITY}}, l[1][2] = {{0.f, 0.f}};
  const int rows[1][2] = {{lane / 4, lane / 4 + 8}};
  if (p.lk > 0) warp_tile<kExactDim, 1, kShortLen, true>(o, m, l, p, t.q, t.k, t.v, 0, rows, 0, lane, D, t.zero);
  store_rows<kExactDim>(o[0], l[0], p, rows[0], s, h, D, lane % 4);
}

template <bool kExactDim>
__global__ void __launch_bounds__(kShortThreads) flash_short_kernel(const FlashParams<bf16> p, int heads,
                                                                     std::int64_t pairs) {
  extern __shared__ __align__(16) unsigned char smem[];
  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  const std::int64_t pair = std::int64_t{blockIdx.x} * kShortWarps + warp;
  if (pair >= pairs) return;
  const std::int64_t s = pair / heads;
  const int h = static_cast<int>(pair % heads);
  const int D = kExactDim ? kMaxHeadDim : p.head_dim;
  const ShortTiles tiles = load_short_tiles<kExactDim>(smem, p, s, h, warp, lane, D);
  cp_async_wait_all();
  __syncwarp();  // the warp's tiles are complete and visible to all its lanes
  short_attend<kExactDim>(p, tiles, s, h, lane, D);
}
}  // namespace fa

// ---------------------------------------------------------------------------------------
// float32 SIMT kernel: 128 threads own 32 query rows, 4 threads per row; each thread scores
// 8 of the 32 keys of a tile and accumulates 32 of the (at most 128) output channels
// (channel c = quad lane + 4 i). Rows padded by one float against bank conflicts.
namespace fa32 {
constexpr int kRows = 32, kKeys = 32, kThreads = 128, kStride = kMaxHeadDim + 1;
constexpr int kSmemBytes = (kRows + 2 * kKeys) * kStride * 4 + kRows * (kKeys + 1) * 4;

__device__ __forceinline__ void load_tile(float* dst, const float* src, std::int64_t stride, int row0, int valid,
                                          int head_dim) {
  for (int e = threadIdx.x; e < kRows * head_dim; e += kThreads) {
    const int r = e / head_dim, col = e % head_dim;
    dst[r * kStride + col] = row0 + r < valid ? src[(row0 + r) * stride + col] : 0.f;
  }
}

// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void __launch_bounds__(kThreads) flash_f32_kernel(const FlashParams<float> p, int heads, int seqs) {
  extern __shared__ __align__(16) unsigned char smem[];
  float* sQ = reinterpret_cast<float*>(smem);
  float* sK = sQ + kRows * kStride;
  float* sV = sK + kKeys * kStride;
  float* sP = sV + kKeys * kStride;  // (kRows, kKeys + 1)

  const int r = threadIdx.x / 4, quad = threadIdx.x % 4;
  const fa::BlockCoords b = fa::block_coords(p, heads, seqs, kRows);  // full row blocks first
  const int q0 = b.q0, h = b.h, D = p.head_dim;
  const std::int64_t s = b.s;
  const int row = q0 + r;
  const float* kg = p.k + s * p.k_seq + std::int64_t{h} * D;
  const float* vg = p.v + s * p.v_seq + std::int64_t{h} * D;
  load_tile(sQ, p.q + s * p.q_seq + std::int64_t{h} * D, p.q_row, q0, p.lq, D);

  constexpr int kPerThread = kKeys / 4, kChannels = kMaxHeadDim / 4;
  float acc[kChannels] = {};
  float m = -INFINITY, l = 0.f;
  const int tiles = key_tiles(q0, kRows, p.lq, p.lk, p.causal, kKeys);
  for (int t = 0; t < tiles; ++t) {
    const int k0 = t * kKeys;
    __syncthreads();  // everyone is done with the previous K, V tiles
    load_tile(sK, kg, p.k_row, k0, p.lk, D);
    load_tile(sV, vg, p.v_row, k0, p.lk, D);
    __syncthreads();

    float sc[kPerThread] = {};
    for (int d = 0; d < D; ++d) {
      const float qd = sQ[r * kStride + d];
#pragma unroll
      for (int j = 0; j < kPerThread; ++j) sc[j] += qd * sK[(quad + 4 * j) * kStride + d];
    }
    float mx = -INFINITY;
#pragma unroll
    for (int j = 0; j < kPerThread; ++j) {
      const int col = k0 + quad + 4 * j;
      float x = sc[j] * p.scale;
      if (p.mask && row < p.lq && col < p.lk) x += p.mask[std::int64_t{row} * p.lk + col];
      if (col >= p.lk || (p.causal && col > row)) x = -INFINITY;
      sc[j] = x;
      mx = fmaxf(mx, x);
    }
    mx = fmaxf(mx, __shfl_xor_sync(0xffffffffu, mx, 1));
    mx = fmaxf(mx, __shfl_xor_sync(0xffffffffu, mx, 2));
    const float m_new = fmaxf(m, mx);
    const float base = m_new == -INFINITY ? 0.f : m_new;
    const float alpha = expf(m - base);
    m = m_new;
    float sum = 0;
#pragma unroll
    for (int j = 0; j < kPerThread; ++j) {
      const float pr = expf(sc[j] - base);
      sum += pr;
      sP[r * (kKeys + 1) + quad + 4 * j] = pr;
    }
    l = l * alpha + sum;
    __syncwarp();  // the row's four threads share one warp
#pragma unroll
    for (int i = 0; i < kChannels; ++i) acc[i] *= alpha;
    for (int j = 0; j < kKeys; ++j) {
      const float pr = sP[r * (kKeys + 1) + j];
#pragma unroll
      for (int i = 0; i < kChannels; ++i) {
        const int c = quad + 4 * i;
        if (c < D) acc[i] += pr * sV[j * kStride + c];
      }
    }
    __syncwarp();  // sP is rewritten by the next tile
  }
  l += __shfl_xor_sync(0xffffffffu, l, 1);
  l += __shfl_xor_sync(0xffffffffu, l, 2);
  if (row >= p.lq) return;
  const float inv = l > 0.f ? 1.0f / l : 0.f;
  float* og = p.o + s * p.o_seq + std::int64_t{row} * p.o_row + std::int64_t{h} * D;
#pragma unroll
  for (int i = 0; i < kChannels; ++i) {
    const int c = quad + 4 * i;
    if (c < D) og[c] = acc[i] * inv;
  }
}
}  // namespace fa32

inline bool aligned_rows(const void* p, std::int64_t seq, std::int64_t row, std::int64_t elems) {
  return reinterpret_cast<std::uintptr_t>(p) % 16 == 0 && seq % elems == 0 && row % elems == 0;
}


inline const char* flash_kernel_name(FlashKernel k) {
  switch (k) {
    case FlashKernel::Auto: return "auto";
    case FlashKernel::Rows64: return "64 rows (4 warps x 16)";
    case FlashKernel::Rows128: return "128 rows (4 warps x 32)";
    case FlashKernel::Rows64Split4: return "64 rows, keys split 4 (8 warps x 32)";
    case FlashKernel::Short: return "short (warp per head)";
    case FlashKernel::Wgmma64: return "wgmma 64 rows, cp.async (1 warpgroup, 64-key tiles)";
    case FlashKernel::Tma64: return "wgmma 64 rows, TMA (1 consumer warpgroup, 128-key tiles)";
    case FlashKernel::Tma128: return "wgmma 128 rows, TMA (2 consumer warpgroups, 128-key tiles)";
    case FlashKernel::TmaPlanned: return "wgmma, TMA, planned (2 consumers, key ranges, 3 stages)";
  }
  return "?";
}

template <class Tile, bool kExactDim>
void launch_flash(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads) {
  const std::int64_t row_blocks = (p.lq + Tile::rows - 1) / Tile::rows;
  allow_dynamic_smem<fa::flash_bf16_kernel<Tile, kExactDim>>(Tile::smem_bytes);
  fa::flash_bf16_kernel<Tile, kExactDim><<<static_cast<unsigned>(row_blocks * heads * seqs), Tile::threads,
                                           Tile::smem_bytes, ctx.stream()>>>(p, static_cast<int>(heads),
                                                                              static_cast<int>(seqs));
}

template <class Tile>
void launch_flash(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads, bool exact) {
  if (exact)
    launch_flash<Tile, true>(ctx, p, seqs, heads);
  else
    launch_flash<Tile, false>(ctx, p, seqs, heads);
}

template <bool kExactDim>
void launch_flash_short(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads) {
  const std::int64_t pairs = seqs * heads, blocks = (pairs + fa::kShortWarps - 1) / fa::kShortWarps;
  allow_dynamic_smem<fa::flash_short_kernel<kExactDim>>(fa::short_smem_bytes(fa::kShortLen, fa::kShortLen));
  fa::flash_short_kernel<kExactDim><<<static_cast<unsigned>(blocks), fa::kShortThreads,
                                      fa::short_smem_bytes(p.lq, p.lk), ctx.stream()>>>(p, static_cast<int>(heads),
                                                                                         pairs);
}

// The Hopper kernels (attention_wgmma.cuh, included at the end): whether this build and device
// have them, and their launch (false: a TMA kernel could not describe these tensors, nothing
// ran). They take head dim 128 with 16-byte aligned rows and no additive mask.
inline bool flash_wgmma_available(const Context& ctx);
inline bool launch_flash_wgmma(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads,
                               FlashKernel kernel, const TmaPlan* plan);
// TmaPlanned's plan under Auto.
inline TmaPlan auto_tma_plan(const Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads);

inline bool short_kernel_fits(const FlashParams<bf16>& p) {
  return p.lq <= fa::kShortLen && p.lk <= fa::kShortLen;
}
inline bool wgmma_kernel_fits(const Context& ctx, const FlashParams<bf16>& p, bool exact) {
  return exact && !p.mask && flash_wgmma_available(ctx);
}

// The kernel Auto runs for these parameters.
inline FlashKernel auto_flash_kernel(const Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs,
                                     std::int64_t heads, bool exact) {
  // By measurement on an H200 (medians, one run, all kernels side by side): sequences of
  // <= 16: a warp per (sequence, head) (MST temporal 87.6 -> 30.0 us); grids that leave
  // multiprocessors without a 64-row block: the keys split over 4 warp groups (TrajDiT
  // 8 x 530: 24.3 -> 20.6 us); long sequences: 128-row blocks, two m-tiles per warp
  // (1 x 16 x 4096: 220 -> 270 TFLOP/s); the rest, 64-row blocks at 16 warps per
  // multiprocessor (VisDiT 16 x 1027: 68.2 -> 61.1 us, MST spatial 160 x 515: 138 -> 119 us).
  //
  // Hopper (sm_90a builds), same run: the TMA kernels; 64-row blocks where they fit in one wave
  // (TrajDiT 8 x 530: 20.5 -> 14.0 us, its last single block 15 x 530: 19.4 -> 13.0 us, VisDiT's
  // 512 x 1027: 30.7 -> 20.4 us), else 128-row blocks (VisDiT 16 x 1027: 61.0 -> 40.3 us, MST
  // spatial 160 x 515: 119.2 -> 95.6 us, its last block 16 x 515: 27.8 -> 18.2 us). Without keys
  // (no tensor map to describe) the cp.async wgmma kernel.
  //
  // The planned TMA kernel (auto_tma_plan) replaces both where ctx.policy().attention_split is on
  // (EPONA_CUDA_ATTN_SPLIT=0: off, the Tma64 / Tma128 kernels as before the plans); same
  // run, from CUDA graphs: VisDiT 16 x 1027 39.5 -> 30.5 us (its short last row blocks cut into
  // key ranges), its last single block 18.9 -> 14.8, MST spatial 97.1 -> 85.4, its last block
  // 16.0 -> 14.8, TrajDiT 8 x 530 12.3 -> 9.9 (consumers sharing 64 rows), its last single block
  // 15 x 530 10.9 -> 7.8 (keys in 3 ranges).
  const std::int64_t blocks64 = (p.lq + 63) / 64 * heads * seqs;
  if (short_kernel_fits(p)) return FlashKernel::Short;
  if (wgmma_kernel_fits(ctx, p, exact))
    return p.lk == 0                                 ? FlashKernel::Wgmma64
           : ctx.policy().attention_split            ? FlashKernel::TmaPlanned
           : blocks64 <= ctx.info().multiprocessors ? FlashKernel::Tma64
                                                    : FlashKernel::Tma128;
  return blocks64 < ctx.info().multiprocessors ? FlashKernel::Rows64Split4
         : p.lq >= 2048                        ? FlashKernel::Rows128
                                               : FlashKernel::Rows64;
}

inline void attention_bf16(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads,
                           bool exact, FlashKernel kernel, const TmaPlan* plan) {
  // 32-key tiles throughout: 64-key tiles cost registers (S), so fewer warps per multiprocessor
  // (measured slower), and with two m-tiles per warp they spill (o and S take 192 registers).
  using Rows64 = fa::Tiling<4, 1, 32, 1, 4>;  // 128 registers: 16 warps per multiprocessor
  using Rows128 = fa::Tiling<4, 2, 32, 1, 2>;  // 2 blocks of 128 threads leave 255 registers
  using Rows64Split4 = fa::Tiling<2, 2, 32, 4, 1>;
  const bool short_fits = short_kernel_fits(p);
  const bool automatic = kernel == FlashKernel::Auto;
  if (automatic) kernel = auto_flash_kernel(ctx, p, seqs, heads, exact);
  switch (kernel) {
    case FlashKernel::Wgmma64:
    case FlashKernel::Tma64:
    case FlashKernel::Tma128:
    case FlashKernel::TmaPlanned:
      EPONA_CHECK(wgmma_kernel_fits(ctx, p, exact),
                  "attention: the wgmma kernels need an sm_90a build on a 9.0 GPU, head dim 128, 16-byte aligned "
                  "rows and no additive mask");
      if (!launch_flash_wgmma(ctx, p, seqs, heads, kernel, plan)) {
        EPONA_CHECK(automatic, "attention: the TMA kernel cannot describe these tensors (", flash_kernel_name(kernel),
                    ")");
        launch_flash_wgmma(ctx, p, seqs, heads, FlashKernel::Wgmma64, nullptr);
      }
      break;
    case FlashKernel::Short:
      EPONA_CHECK(short_fits, "attention: the short kernel takes at most ", fa::kShortLen, " queries and keys");
      if (exact)
        launch_flash_short<true>(ctx, p, seqs, heads);
      else
        launch_flash_short<false>(ctx, p, seqs, heads);
      break;
    case FlashKernel::Rows128: launch_flash<Rows128>(ctx, p, seqs, heads, exact); break;
    case FlashKernel::Rows64Split4: launch_flash<Rows64Split4>(ctx, p, seqs, heads, exact); break;
    default: launch_flash<Rows64>(ctx, p, seqs, heads, exact); break;
  }
}

template <class T>
FlashParams<T> flash_params(const T* q, const T* k, const T* v, T* o, const AttentionShape& a) {
  const float scale = a.scale != 0 ? a.scale : 1.0f / std::sqrt(static_cast<float>(a.head_dim));
  FlashParams<T> p{q,       k,       v,       o,       a.q_seq, a.q_row, a.k_seq, a.k_row, a.v_seq,
                   a.v_row, a.o_seq, a.o_row, static_cast<int>(a.lq), static_cast<int>(a.lk),
                   static_cast<int>(a.head_dim), scale, a.mask == Mask::Causal, a.additive_mask};
  if constexpr (std::is_same_v<T, bf16>) p.scale = scale * fa::kLog2e;  // softmax in base 2: exp(x) = exp2(x log2 e)
  return p;
}

// Head dim 128 with every row 16-byte aligned: the specialised bf16 paths (cp.async, wgmma).
inline bool exact_head_dim(const FlashParams<bf16>& p) {
  return p.head_dim == kMaxHeadDim && aligned_rows(p.q, p.q_seq, p.q_row, 8) && aligned_rows(p.k, p.k_seq, p.k_row, 8) &&
         aligned_rows(p.v, p.v_seq, p.v_row, 8) && aligned_rows(p.o, p.o_seq, p.o_row, 8);
}

// The bf16 kernel attention() runs for these arguments (tests: which kernel Auto picks).
inline FlashKernel auto_flash_kernel(const Context& ctx, const bf16* q, const bf16* k, const bf16* v, bf16* o,
                                     const AttentionShape& a) {
  const FlashParams<bf16> p = flash_params(q, k, v, o, a);
  return auto_flash_kernel(ctx, p, a.seqs, a.heads, exact_head_dim(p));
}

// attention() with the bf16 kernel chosen by the caller (tests, benchmarks); plan: TmaPlanned's
// (null: Auto's).
template <class T>
void attention(Context& ctx, const T* q, const T* k, const T* v, T* o, const AttentionShape& a, FlashKernel kernel,
               const TmaPlan* plan = nullptr) {
  static_assert(is_device_float<T>, "attention takes float or bf16");
  EPONA_CHECK(a.seqs >= 0 && a.heads >= 0 && a.lq >= 0 && a.lk >= 0, "attention: negative extent");
  EPONA_CHECK(a.head_dim >= 1 && a.head_dim <= kMaxHeadDim, "attention: head_dim ", a.head_dim, " unsupported (1..",
              kMaxHeadDim, ")");
  EPONA_CHECK(a.lq <= INT32_MAX && a.lk <= INT32_MAX, "attention: sequence too long (lq ", a.lq, ", lk ", a.lk, ")");
  EPONA_CHECK(a.heads <= 65535 && a.seqs <= 65535, "attention: ", a.seqs, " sequences x ", a.heads,
              " heads exceed one launch (65535 each)");
  EPONA_CHECK(q && k && v && o, "attention: null tensor");
  if (a.seqs == 0 || a.heads == 0 || a.lq == 0) return;

  FlashParams<T> p = flash_params(q, k, v, o, a);
  if constexpr (std::is_same_v<T, bf16>) {
    attention_bf16(ctx, p, a.seqs, a.heads, exact_head_dim(p), kernel, plan);
  } else {
    namespace fa32 = detail::fa32;
    const std::int64_t blocks = (a.lq + fa32::kRows - 1) / fa32::kRows * a.heads * a.seqs;
    allow_dynamic_smem<fa32::flash_f32_kernel<>>(fa32::kSmemBytes);
    fa32::flash_f32_kernel<><<<static_cast<unsigned>(blocks), fa32::kThreads, fa32::kSmemBytes, ctx.stream()>>>(
        p, static_cast<int>(a.heads), static_cast<int>(a.seqs));
  }
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace detail

template <class T>
void attention(Context& ctx, const T* q, const T* k, const T* v, T* o, const AttentionShape& a) {
  detail::attention(ctx, q, k, v, o, a, detail::FlashKernel::Auto);
}

}  // namespace epona::cuda

#include "epona/cuda/attention/attention_wgmma.cuh"  // the Hopper kernel declared above
