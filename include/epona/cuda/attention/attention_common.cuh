// epona/cuda/attention/attention_common.cuh — what the flash-attention kernels of attention.cuh (mma.sync)
// and attention_wgmma.cuh (Hopper) share: the kernels' parameters, the tile primitives, online
// softmax, masking, the output store and block coordinates, and the names of the bf16 kernels and
// the TMA plan. Its own header so that the two kernel headers include it and not each other.
#pragma once

#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>

#include "epona/core/env.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/ptx/mma.cuh"

namespace epona::cuda {

using epona::AttentionShape;
using epona::Mask;

namespace detail {

inline constexpr int kMaxHeadDim = 128;

template <class T>
struct FlashParams {
  const T *q, *k, *v;
  T* o;
  std::int64_t q_seq, q_row, k_seq, k_row, v_seq, v_row, o_seq, o_row;
  int lq, lk, head_dim;
  float scale;  // bf16 kernel: scale * log2(e) (softmax in base 2); float32 kernel: scale
  bool causal;
  const float* mask;
};

// Number of key tiles query rows [q0, q0 + rows) need: all of them, or up to the diagonal.
__device__ __forceinline__ int key_tiles(int q0, int rows, int lq, int lk, bool causal, int tile) {
  int keys = lk;
  if (causal) keys = min(lk, min(q0 + rows, lq));
  return (keys + tile - 1) / tile;
}

// ---------------------------------------------------------------------------------------
// bf16 tensor-core kernels (mma.sync m16n8k16, float32 accumulators, softmax in base 2).
// A warp owns kM x 16 query rows; K and V tiles of 32 keys stream through shared memory in
// two buffers (tile t+1 loads while tile t is computed: one barrier per tile), rows padded by
// 16 bytes so that ldmatrix is free of bank conflicts. Two m-tiles per warp share every K and
// V fragment read from shared memory, halving that traffic per tensor-core operation.
// kExactDim: head_dim == 128 with 16-byte aligned rows (cp.async loads); otherwise any
// head_dim <= 128, zero-padded, with guarded loads.
namespace fa {
constexpr int kStride = kMaxHeadDim + 8;  // shared-memory row stride, in bf16 elements
constexpr int kDimTiles = kMaxHeadDim / 8;
constexpr float kLog2e = 1.4426950408889634f;

// 2^x by the special-function unit alone (exp2f adds a denormal-range fix-up around it;
// results below 2^-126 flush to zero, far under what bf16 P or the float32 sums resolve).
__device__ __forceinline__ float exp2_fast(float x) {
  float y;
  asm("ex2.approx.ftz.f32 %0, %1;\n" : "=f"(y) : "f"(x));
  return y;
}
__device__ __forceinline__ unsigned pack_bf16(float lo, float hi) {
  const __nv_bfloat162 v = __floats2bfloat162_rn(lo, hi);
  return *reinterpret_cast<const unsigned*>(&v);
}
// Sum over the four threads of a quad (the threads that share an accumulator row).
__device__ __forceinline__ float quad_sum(float x) {
  x += __shfl_xor_sync(0xffffffffu, x, 1);
  return x + __shfl_xor_sync(0xffffffffu, x, 2);
}

// A thread's partial results for its two accumulator rows over some of the keys: o
// (unnormalised), the running max m (base 2) and its share l of the row sums. In a slot, value v
// at at(v): o[nt][c] at 4 nt + c, then m[0], m[1], l[0], l[1].
constexpr int kPartialValues = kDimTiles * 4 + 4;
template <class At>
__device__ __forceinline__ void stash_partial(const float (&o)[kDimTiles][4], const float (&m)[2],
                                              const float (&l)[2], At at) {
#pragma unroll
  for (int nt = 0; nt < kDimTiles; ++nt)
#pragma unroll
    for (int c = 0; c < 4; ++c) at(4 * nt + c) = o[nt][c];
#pragma unroll
  for (int i = 0; i < 2; ++i) at(kDimTiles * 4 + i) = m[i], at(kDimTiles * 4 + 2 + i) = l[i];
}
// Folds the stashed partial results of the same rows over other keys into (o, m, l), as online
// softmax over both key sets would.
template <class At>
__device__ __forceinline__ void fold_partial(float (&o)[kDimTiles][4], float (&m)[2], float (&l)[2], At at) {
#pragma unroll
  for (int i = 0; i < 2; ++i) {
    const float m_other = at(kDimTiles * 4 + i);
    const float m_new = fmaxf(m[i], m_other);
    const float base = m_new == -INFINITY ? 0.f : m_new;
    const float mine = exp2_fast(m[i] - base), other = exp2_fast(m_other - base);
    m[i] = m_new;
    l[i] = l[i] * mine + at(kDimTiles * 4 + 2 + i) * other;
#pragma unroll
    for (int nt = 0; nt < kDimTiles; ++nt)
#pragma unroll
      for (int e = 0; e < 2; ++e) o[nt][2 * i + e] = o[nt][2 * i + e] * mine + at(4 * nt + 2 * i + e) * other;
  }
}

// Rows [row0, row0 + count) of one head (row i at src + i * stride) into shared memory,
// spread over `threads` threads of which this is `thread`; rows past `valid` and channels
// past head_dim become zeros (a zero V row times P = 0 stays 0; garbage could be NaN).
template <bool kExactDim>
__device__ __forceinline__ void load_tile(bf16* dst, const bf16* src, std::int64_t stride, int row0, int count,
                                          int valid, int head_dim, int thread, int threads) {
  if constexpr (kExactDim) {
    constexpr int kChunks = kMaxHeadDim / 8;  // 16-byte chunks per row
    for (int c = thread; c < count * kChunks; c += threads) {
      const int r = c / kChunks, col = (c % kChunks) * 8;
      bf16* d = dst + r * kStride + col;
      if (row0 + r < valid)
        cp_async_16(d, src + (row0 + r) * stride + col);
      else
        *reinterpret_cast<uint4*>(d) = make_uint4(0, 0, 0, 0);
    }
  } else {
    for (int e = thread; e < count * kMaxHeadDim; e += threads) {
      const int r = e / kMaxHeadDim, col = e % kMaxHeadDim;
      bf16 val{};
      if (row0 + r < valid && col < head_dim) val = src[(row0 + r) * stride + col];
      dst[r * kStride + col] = val;
    }
  }
}

// S = Q K(t)ᵀ for one warp's kM x 16 query rows (sQ: its first row) and kKeys keys.
template <bool kExactDim, int kM, int kKeys>
__device__ __forceinline__ void warp_scores(float (&sc)[kM][kKeys / 8][4], const bf16* sQ, const bf16* sK, int lane,
                                            int D) {
#pragma unroll
  for (int kk = 0; kk < kMaxHeadDim / 16; ++kk) {
    if (!kExactDim && kk * 16 >= D) break;
    unsigned a[kM][4];
#pragma unroll
    for (int mt = 0; mt < kM; ++mt)
      ldmatrix_x4(a[mt], sQ + (mt * 16 + (lane & 15)) * kStride + kk * 16 + (lane >> 4) * 8);
#pragma unroll
    for (int n2 = 0; n2 < kKeys / 16; ++n2) {
      unsigned b[4];
      ldmatrix_x4(b, sK + (n2 * 16 + (lane & 7) + ((lane >> 4) << 3)) * kStride + kk * 16 + ((lane >> 3) & 1) * 8);
#pragma unroll
      for (int mt = 0; mt < kM; ++mt) {
        mma_bf16(sc[mt][2 * n2], a[mt], b[0], b[1]);
        mma_bf16(sc[mt][2 * n2 + 1], a[mt], b[2], b[3]);
      }
    }
  }
}

// Folds the raw scores of key tile k0 (one m-tile) into the running max m and sum l of this
// thread's two rows (base 2), leaving P = exp2(S·scale - m) in sc and in alpha the factors by
// which the output accumulators must be rescaled to the new max. kMasked: the tile has keys
// past lk, past the causal diagonal of some row, or an additive mask; those scores are scaled
// and masked one by one. Unmasked tiles (most of them) take the max of the raw scores and fold
// the scale into the exponent's FMA, which needs scale > 0 (the caller routes any other scale
// to kMasked).
template <bool kMasked, int kKeyTiles>
__device__ __forceinline__ void softmax_tile(float (&sc)[kKeyTiles][4], float (&m)[2], float (&l)[2],
                                             float (&alpha)[2], const FlashParams<bf16>& p, const int (&rows)[2],
                                             int k0, int tq) {
  const float scale = kMasked ? 1.0f : p.scale;  // masked scores are scaled in place below
#pragma unroll
  for (int i = 0; i < 2; ++i) {
    float mx = -INFINITY;
#pragma unroll
    for (int nt = 0; nt < kKeyTiles; ++nt)
#pragma unroll
      for (int e = 0; e < 2; ++e) {
        float x = sc[nt][2 * i + e];
        if constexpr (kMasked) {
          x *= p.scale;
          const int col = k0 + nt * 8 + 2 * tq + e;
          if (p.mask && rows[i] < p.lq && col < p.lk) x += p.mask[std::int64_t{rows[i]} * p.lk + col] * kLog2e;
          if (col >= p.lk || (p.causal && col > rows[i])) x = -INFINITY;
          sc[nt][2 * i + e] = x;
        }
        mx = fmaxf(mx, x);
      }
    mx = fmaxf(mx, __shfl_xor_sync(0xffffffffu, mx, 1));  // the row's four threads
    mx = fmaxf(mx, __shfl_xor_sync(0xffffffffu, mx, 2));
    const float m_new = fmaxf(m[i], mx * scale);
    const float base = m_new == -INFINITY ? 0.f : m_new;  // a row masked so far stays all zero
    alpha[i] = exp2_fast(m[i] - base);
    m[i] = m_new;
    float sum = 0;
#pragma unroll
    for (int nt = 0; nt < kKeyTiles; ++nt)
#pragma unroll
      for (int e = 0; e < 2; ++e) {
        const float pr = exp2_fast(fmaf(sc[nt][2 * i + e], scale, -base));
        sc[nt][2 * i + e] = pr;
        sum += pr;
      }
    l[i] = l[i] * alpha[i] + sum;  // this thread's share of the row; reduced over the quad at the end
  }
}

__device__ __forceinline__ void rescale_rows(float (&o)[kDimTiles][4], const float (&alpha)[2]) {
#pragma unroll
  for (int nt = 0; nt < kDimTiles; ++nt) {
    o[nt][0] *= alpha[0], o[nt][1] *= alpha[0];
    o[nt][2] *= alpha[1], o[nt][3] *= alpha[1];
  }
}

// softmax_tile, then the output accumulators rescaled at once.
template <bool kMasked, int kKeyTiles>
__device__ __forceinline__ void online_softmax(float (&sc)[kKeyTiles][4], float (&m)[2], float (&l)[2],
                                               float (&o)[kDimTiles][4], const FlashParams<bf16>& p,
                                               const int (&rows)[2], int k0, int tq) {
  float alpha[2];
  softmax_tile<kMasked>(sc, m, l, alpha, p, rows, k0, tq);
  rescale_rows(o, alpha);
}

// O += P V(t): the S accumulators of two adjacent key tiles form one A fragment of P. With
// kZeroPast, V's rows from `valid` on are read from zero_row instead (one row of zeros: P is 0
// there, and 0 times garbage could be NaN), so the tile need not hold them.
template <bool kExactDim, int kM, int kKeys, bool kZeroPast = false>
__device__ __forceinline__ void warp_pv(float (&o)[kM][kDimTiles][4], const float (&sc)[kM][kKeys / 8][4],
                                        const bf16* sV, int lane, int D, int valid = 0,
                                        const bf16* zero_row = nullptr) {
#pragma unroll
  for (int kk = 0; kk < kKeys / 16; ++kk) {
    unsigned a[kM][4];
#pragma unroll
    for (int mt = 0; mt < kM; ++mt) {
      a[mt][0] = pack_bf16(sc[mt][2 * kk][0], sc[mt][2 * kk][1]);
      a[mt][1] = pack_bf16(sc[mt][2 * kk][2], sc[mt][2 * kk][3]);
      a[mt][2] = pack_bf16(sc[mt][2 * kk + 1][0], sc[mt][2 * kk + 1][1]);
      a[mt][3] = pack_bf16(sc[mt][2 * kk + 1][2], sc[mt][2 * kk + 1][3]);
    }
#pragma unroll
    for (int n2 = 0; n2 < kMaxHeadDim / 16; ++n2) {
      if (!kExactDim && n2 * 16 >= D) break;
      unsigned b[4];
      const int row = kk * 16 + (lane & 7) + ((lane >> 3) & 1) * 8, col = n2 * 16 + (lane >> 4) * 8;
      ldmatrix_x4_trans(b, (kZeroPast && row >= valid ? zero_row : sV + row * kStride) + col);
#pragma unroll
      for (int mt = 0; mt < kM; ++mt) {
        mma_bf16(o[mt][2 * n2], a[mt], b[0], b[1]);
        mma_bf16(o[mt][2 * n2 + 1], a[mt], b[2], b[3]);
      }
    }
  }
}

// Normalises and stores rows g and g + 8 of one m-tile (columns 2 tq, 2 tq + 1 of each tile).
template <bool kExactDim>
__device__ __forceinline__ void store_rows(const float (&o)[kDimTiles][4], const float (&l)[2],
                                           const FlashParams<bf16>& p, const int (&rows)[2], std::int64_t s, int h,
                                           int D, int tq) {
#pragma unroll
  for (int i = 0; i < 2; ++i) {
    const float sum = quad_sum(l[i]);
    const float inv = sum > 0.f ? 1.0f / sum : 0.f;
    if (rows[i] >= p.lq) continue;
    bf16* og = p.o + s * p.o_seq + std::int64_t{rows[i]} * p.o_row + std::int64_t{h} * D;
#pragma unroll
    for (int nt = 0; nt < kDimTiles; ++nt) {
      const int col = nt * 8 + 2 * tq;
      const float v0 = o[nt][2 * i] * inv, v1 = o[nt][2 * i + 1] * inv;
      if constexpr (kExactDim) {
        *reinterpret_cast<unsigned*>(og + col) = pack_bf16(v0, v1);
      } else {
        if (col < D) og[col] = from_f32<bf16>(v0);
        if (col + 1 < D) og[col + 1] = from_f32<bf16>(v1);
      }
    }
  }
}

// Whether key tile [k0, k0 + keys) of query rows [row0, row0 + 16) needs per-score masking.
__device__ __forceinline__ bool tile_masked(const FlashParams<bf16>& p, int row0, int k0, int keys) {
  return !(p.scale > 0.f) || p.mask || k0 + keys > p.lk || (p.causal && k0 + keys - 1 > row0);
}

// One key tile for one warp: scores, softmax (per m-tile), O += P V (kZeroPast: V's rows past
// lk read from zero_row, as warp_pv).
template <bool kExactDim, int kM, int kKeys, bool kZeroPast = false>
__device__ __forceinline__ void warp_tile(float (&o)[kM][kDimTiles][4], float (&m)[kM][2], float (&l)[kM][2],
                                          const FlashParams<bf16>& p, const bf16* sQ, const bf16* sK,
                                          const bf16* sV, int row0, const int (&rows)[kM][2], int k0, int lane,
                                          int D, const bf16* zero_row = nullptr) {
  float sc[kM][kKeys / 8][4] = {};
  warp_scores<kExactDim, kM, kKeys>(sc, sQ, sK, lane, D);
#pragma unroll
  for (int mt = 0; mt < kM; ++mt) {
    if (tile_masked(p, row0 + mt * 16, k0, kKeys))
      online_softmax<true>(sc[mt], m[mt], l[mt], o[mt], p, rows[mt], k0, lane % 4);
    else
      online_softmax<false>(sc[mt], m[mt], l[mt], o[mt], p, rows[mt], k0, lane % 4);
  }
  warp_pv<kExactDim, kM, kKeys, kZeroPast>(o, sc, sV, lane, D, p.lk - k0, zero_row);
}

// A block: kGroups groups of kWarps warps with kM m-tiles each, over rows = 16 kWarps kM
// query rows of one (sequence, head); key tiles of kKeys. Group g takes key tiles g,
// g + kGroups, ...; the groups' partial results (o, m, l) merge through shared memory at
// the end. Splitting the keys puts more warps on the same rows where the grid is too small
// to fill the multiprocessors (TrajDiT: 8 heads x 530 rows). Each group waits on its own
// named barrier, so the groups run as independently as separate blocks (one block-wide
// barrier per tile measured far slower). Shared memory: Q, then two stages of a (K, V)
// tile per group (reused for the merge). kMinBlocks: blocks per multiprocessor the register
// allocation must allow.
template <int kWarps, int kM, int kKeys, int kGroups, int kMinBlocks>
struct Tiling {
  static constexpr int warps = kWarps, m_tiles = kM, keys = kKeys, groups = kGroups;
  static constexpr int rows = 16 * kWarps * kM, threads = 32 * kWarps * kGroups;
  static constexpr int kv_elems = 2 * kKeys * kStride;  // one K and one V tile
  // Per thread: o, then m and l of each m-tile.
  static constexpr int merge_values = kM * kPartialValues;
  static constexpr int merge_bytes = (kGroups - 1) * kWarps * 32 * merge_values * 4;
  static constexpr int kv_bytes = 2 * kGroups * kv_elems * 2;
  static constexpr int smem_bytes = rows * kStride * 2 + (kv_bytes > merge_bytes ? kv_bytes : merge_bytes);
  static constexpr int min_blocks = kMinBlocks;
};

// Group g > 0 leaves its partial results in slot g - 1 of `red`; group 0 folds them into its
// own (each thread's partners hold the same rows and columns).
template <class Tile>
__device__ __forceinline__ void merge_groups(float (&o)[Tile::m_tiles][kDimTiles][4], float (&m)[Tile::m_tiles][2],
                                             float (&l)[Tile::m_tiles][2], float* red, int group, int warp_in_group,
                                             int lane) {
  constexpr int kM = Tile::m_tiles, kValues = Tile::merge_values, kSlot = Tile::warps * 32 * kValues;
  // Value v of m-tile mt of this thread at (warp_in_group * kValues + mt * kPartialValues + v) * 32 + lane:
  // lanes hit consecutive words.
  const auto slot_of = [&](int g, int mt) {
    float* slot = red + (g - 1) * kSlot + (warp_in_group * kValues + mt * kPartialValues) * 32 + lane;
    return [slot](int v) -> float& { return slot[v * 32]; };
  };
  __syncthreads();  // every group is done with the K and V tiles
  if (group > 0) {
#pragma unroll
    for (int mt = 0; mt < kM; ++mt) stash_partial(o[mt], m[mt], l[mt], slot_of(group, mt));
  }
  __syncthreads();
  if (group > 0) return;
  for (int g = 1; g < Tile::groups; ++g)
#pragma unroll
    for (int mt = 0; mt < kM; ++mt) fold_partial(o[mt], m[mt], l[mt], slot_of(g, mt));
}

// Block -> (sequence, head, first query row) for blocks of `rows` query rows. The row blocks
// of `rows` rows come first, the short last row block of every (sequence, head) after them,
// so that the grid's tail is short work (VisDiT: 16 heads x 1027 rows = 256 full blocks of 64
// rows + 16 of 3).
struct BlockCoords {
  std::int64_t s;
  int h, q0;
};
template <class T>
__device__ __forceinline__ BlockCoords block_coords(const FlashParams<T>& p, int heads, int seqs, int rows) {
  const int full = p.lq / rows;
  const std::int64_t pairs = std::int64_t{heads} * seqs, b = blockIdx.x;
  std::int64_t pair;
  int rb;
  if (b < full * pairs) {
    pair = b / full;
    rb = static_cast<int>(b % full);
    if (p.causal) rb = full - 1 - rb;  // causal: the longest rows first
  } else {
    pair = b - full * pairs;
    rb = full;
  }
  return {pair / heads, static_cast<int>(pair % heads), rb * rows};
}
}  // namespace fa


// Which bf16 kernel runs: Auto picks by shape; the others are for tests and benchmarks.
// Wgmma64 and the Tma kernels: the Hopper kernels (attention_wgmma.cuh).
enum class FlashKernel { Auto, Rows64, Rows128, Rows64Split4, Short, Wgmma64, Tma64, Tma128, TmaPlanned };

inline bool is_wgmma(FlashKernel k) {
  return k == FlashKernel::Wgmma64 || k == FlashKernel::Tma64 || k == FlashKernel::Tma128 ||
         k == FlashKernel::TmaPlanned;
}

// How TmaPlanned (a producer and two consumer warpgroups) covers a call. rows: query rows per
// block; 64: the consumers share them and take alternate key tiles (merged in shared memory at
// the end), 128: 64 each, except in a last row block of <= 64 rows, which is shared
// (share_rows). splits > 1: each row block's key tiles are cut into that many ranges, one block
// each, whose float32 partial results a combine kernel normalises (tail_only: only the last,
// partial row block). narrow_last: the sequence's last key tile is multiplied only as wide as
// its keys (32 or 64). A single wave of blocks that leaves multiprocessors idle, or a last wave
// of full-length blocks for a few rows, is what the plan avoids. ctas > 0 (persistent): at most
// that many CTAs take the row blocks in turn (CTA i: i, i + grid, ...), each producer loading
// the next block's Q and first key tiles while its consumers finish and store the last; 0: one
// CTA per row block.
struct TmaPlan {
  int rows = 128;
  int splits = 1;
  bool tail_only = false;
  bool share_rows = true;
  bool narrow_last = true;
  int ctas = 0;
};
inline constexpr int kMaxSplits = 16;
// Partial results of split blocks live in one buffer of the context (attention_wgmma.cuh).
inline constexpr std::int64_t kSplitPartialBytes = std::int64_t{8} << 20;

}  // namespace detail
}  // namespace epona::cuda
