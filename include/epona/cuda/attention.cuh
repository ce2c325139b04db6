// epona/cuda/attention.cuh — fused scaled-dot-product attention on the GPU (flash attention:
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
#include "epona/cuda/context.hpp"
#include "epona/cuda/device.cuh"
#include "epona/cuda/mma.cuh"

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

// EPONA_CUDA_ATTN_SPLIT=0: Auto takes the Tma64 / Tma128 kernels as before the plans (to time
// both in one binary); set_attention_split switches at run time.
inline std::atomic<bool>& attention_split_setting() {
  static std::atomic<bool> on{env_flag("EPONA_CUDA_ATTN_SPLIT", true)};
  return on;
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
  // The planned TMA kernel (auto_tma_plan) replaces both where EPONA_CUDA_ATTN_SPLIT is on; same
  // run, from CUDA graphs: VisDiT 16 x 1027 39.5 -> 30.5 us (its short last row blocks cut into
  // key ranges), its last single block 18.9 -> 14.8, MST spatial 97.1 -> 85.4, its last block
  // 16.0 -> 14.8, TrajDiT 8 x 530 12.3 -> 9.9 (consumers sharing 64 rows), its last single block
  // 15 x 530 10.9 -> 7.8 (keys in 3 ranges).
  const std::int64_t blocks64 = (p.lq + 63) / 64 * heads * seqs;
  if (short_kernel_fits(p)) return FlashKernel::Short;
  if (wgmma_kernel_fits(ctx, p, exact))
    return p.lk == 0                                 ? FlashKernel::Wgmma64
           : attention_split_setting().load()        ? FlashKernel::TmaPlanned
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
    allow_dynamic_smem<fa32::flash_f32_kernel>(fa32::kSmemBytes);
    fa32::flash_f32_kernel<<<static_cast<unsigned>(blocks), fa32::kThreads, fa32::kSmemBytes, ctx.stream()>>>(
        p, static_cast<int>(a.heads), static_cast<int>(a.seqs));
  }
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace detail

template <class T>
void attention(Context& ctx, const T* q, const T* k, const T* v, T* o, const AttentionShape& a) {
  detail::attention(ctx, q, k, v, o, a, detail::FlashKernel::Auto);
}

// Whether Auto takes the planned TMA kernel (EPONA_CUDA_ATTN_SPLIT; tests and benchmarks
// compare it with the unplanned kernels in one process).
inline void set_attention_split(bool on) { detail::attention_split_setting().store(on); }

}  // namespace epona::cuda

#include "epona/cuda/attention_wgmma.cuh"  // the Hopper kernel declared above
