// epona/cuda/attention/attention_wgmma.cuh — the Hopper (sm_90a) flash-attention kernels for bf16 with
// head dim 128: warpgroup MMA (wgmma), S = Q Kᵀ with both operands in shared memory and O += P V
// with P in registers; online softmax, masking and the output store shared with attention.cuh's
// mma.sync kernels through attention_common.cuh (same float32 accumulation, base-2 softmax and
// bf16 P). Tiles arrive by cp.async from the computing threads, or by the tensor memory
// accelerator (TMA) from a producer warp while consumer warpgroups compute; the planned variant
// sizes its blocks to fill the GPU (consumers sharing a block's rows split its key tiles, key
// ranges over blocks are merged by a combine kernel). Included at the end of attention.cuh,
// which declares its entry points; other targets compile empty kernel bodies.
#pragma once

#include <cuda.h>  // CUtensorMap (the encoder itself is fetched from the driver at run time)

#include <algorithm>
#include <cstdint>
#include <string>

#include "epona/cuda/attention/attention_common.cuh"
#include "epona/cuda/ptx/wgmma.cuh"

namespace epona::cuda::detail {

namespace fa {

// ---------------------------------------------------------------------------------------
// Hopper primitives. Shared-memory tiles of 128 bf16 channels per row are stored as two
// column halves of 64 channels (128 bytes a row), 8-row atoms of 1024 bytes, 16-byte chunk c
// of row r at position c ^ (r % 8) in its row: the canonical 128-byte swizzle that the
// wgmma matrix descriptors name (both for K-major operands, Q and K, and for the N-major V).
// Tiles start at 1024-byte boundaries, so the swizzle phase is the address's own.

__device__ __forceinline__ unsigned swizzled_offset(int row, int chunk, int rows) {
  return (chunk >> 3) * rows * kRowBytes + row * kRowBytes + (((chunk & 7) ^ (row & 7)) << 4);
}

// 16 bytes global -> shared; bytes = 0 writes zeros (rows past the sequence end).
__device__ __forceinline__ void cp_async_16_or_zero(unsigned dst, const void* src, int bytes) {
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16, %2;\n" ::"r"(dst), "l"(src), "r"(bytes));
}

// Rows [row0, row0 + kRows) of one head (row i at src + i * stride, 128 channels) into the
// swizzled tile at dst, spread over kThreads threads; rows past `valid` become zeros (a zero
// V row times P = 0 stays 0; garbage could be NaN). Consecutive threads take consecutive
// chunks of a row: coalesced reads, and the swizzle spreads the writes over all banks.
template <int kRows, int kThreads>
__device__ __forceinline__ void load_swizzled(unsigned dst, const bf16* src, std::int64_t stride, int row0, int valid,
                                              int thread) {
  constexpr int kChunks = kMaxHeadDim / 8;
  static_assert(kRows * kChunks % kThreads == 0);
#pragma unroll
  for (int i = 0; i < kRows * kChunks / kThreads; ++i) {
    const int c = thread + i * kThreads, r = c / kChunks, chunk = c % kChunks;
    const bool inside = row0 + r < valid;
    const bf16* g = src + (inside ? (row0 + r) * stride : std::int64_t{0}) + chunk * 8;
    cp_async_16_or_zero(dst + swizzled_offset(r, chunk, kRows), g, inside ? 16 : 0);
  }
}

// d (64 x 128) += A (64 x 16 bf16 in registers, mma.sync's A fragment per warp) B (16 x 128,
// shared, N-major: the transpose bit).
__device__ __forceinline__ void wgmma_rs(float (&d)[16][4], const unsigned (&a)[4], std::uint64_t b) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %69, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n128k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, %32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, %48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}, {%64, %65, %66, %67}, %68, p, 1, 1, 1;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_16(d)
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "l"(b), "r"(1));
}

// A block: kGroups consumer warpgroups, each owning 64 query rows of one (sequence, head),
// sharing key tiles of kKeys keys (K and V) that stream through two shared-memory stages.
// kMinBlocks: blocks per multiprocessor the registers and shared memory must allow.
template <int kGroups, int kKeys, int kMinBlocks>
struct WgmmaTiling {
  static constexpr int groups = kGroups, keys = kKeys, rows = 64 * kGroups, threads = 128 * kGroups;
  static constexpr int min_blocks = kMinBlocks;
  static constexpr int q_bytes = 64 * kMaxHeadDim * 2;       // one group's Q tile
  static constexpr int kv_bytes = 2 * kKeys * kMaxHeadDim * 2;  // K and V tiles of one stage
  static constexpr int smem_bytes = kGroups * q_bytes + 2 * kv_bytes + kAtomBytes;  // + alignment slack
  static_assert(kKeys % 16 == 0 && kKeys <= 256);
};


// Issues S = Q Kᵀ for the warpgroup's 64 rows and the first kKeys keys of a tile of kTileKeys
// (kKeys < kTileKeys: the sequence's last, narrow tile): 8 steps of 16 channels; a step moves
// 32 bytes along the swizzled rows (the hardware applies the swizzle to the full address).
template <int kKeys, int kTileKeys>
__device__ __forceinline__ void issue_scores(float (&sc)[kKeys / 8][4], unsigned sQ, unsigned sK) {
#pragma unroll
  for (int kk = 0; kk < kMaxHeadDim / 16; ++kk) {
    const unsigned step = (kk % 4) * 32;  // within the 128-byte row of the half kk / 4
    wgmma_ss(sc, smem_desc(sQ + (kk / 4) * 64 * kRowBytes + step, 16, kAtomBytes),
             smem_desc(sK + (kk / 4) * kTileKeys * kRowBytes + step, 16, kAtomBytes), kk > 0);
  }
}

// P (the softmax's output in sc) rounded to bf16: the A fragments of P V, 16 keys per step.
template <int kKeys>
__device__ __forceinline__ void pack_p(unsigned (&a)[kKeys / 16][4], const float (&sc)[kKeys / 8][4]) {
#pragma unroll
  for (int kk = 0; kk < kKeys / 16; ++kk) {
    a[kk][0] = pack_bf16(sc[2 * kk][0], sc[2 * kk][1]);
    a[kk][1] = pack_bf16(sc[2 * kk][2], sc[2 * kk][3]);
    a[kk][2] = pack_bf16(sc[2 * kk + 1][0], sc[2 * kk + 1][1]);
    a[kk][3] = pack_bf16(sc[2 * kk + 1][2], sc[2 * kk + 1][3]);
  }
}

// Issues O += P V over the first kKeys keys of a V tile of kTileKeys; a step of 16 keys is two
// 8-key atoms (2048 bytes) further, the two 64-channel halves kTileKeys rows apart.
template <int kKeys, int kTileKeys>
__device__ __forceinline__ void issue_pv(float (&o)[kDimTiles][4], const unsigned (&a)[kKeys / 16][4], unsigned sV) {
#pragma unroll
  for (int kk = 0; kk < kKeys / 16; ++kk)
    wgmma_rs(o, a[kk], smem_desc(sV + kk * 2 * kAtomBytes, kTileKeys * kRowBytes, kAtomBytes));
}

template <int kKeys, int kTileKeys = kKeys>
__device__ __forceinline__ void wg_scores(float (&sc)[kKeys / 8][4], unsigned sQ, unsigned sK) {
  wgmma_fence();
  issue_scores<kKeys, kTileKeys>(sc, sQ, sK);
  wgmma_commit();
  wgmma_wait_all();
  pin(sc);
}

template <int kKeys, int kTileKeys = kKeys>
__device__ __forceinline__ void wg_accumulate_pv(float (&o)[kDimTiles][4], const float (&sc)[kKeys / 8][4],
                                                 unsigned sV) {
  unsigned a[kKeys / 16][4];
  pack_p<kKeys>(a, sc);
  wgmma_fence();
  issue_pv<kKeys, kTileKeys>(o, a, sV);
  wgmma_commit();
  wgmma_wait_all();
  pin(o);
  pin(a);
}

// One block: Q of every group and the first key tile load together; then per key tile one
// barrier (tile t landed and every group is done with tile t - 1's stage, which tile t + 1
// then loads into while tile t is computed). A group whose rows all lie past lq, or (causal)
// before the tile's first key, skips the tile's math but not its loads and barriers.
template <class Tile>
__global__ void __launch_bounds__(Tile::threads, Tile::min_blocks)
    flash_wgmma_kernel(const FlashParams<bf16> p, int heads, int seqs) {
  wait_for_producer();  // may start before its producer ends (launch_after)
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  constexpr int kKeys = Tile::keys, kThreads = Tile::threads;
  extern __shared__ __align__(16) unsigned char smem[];
  const unsigned sQ = first_atom(smem);
  const unsigned sKV = sQ + Tile::groups * Tile::q_bytes;
  const auto stage = [&](int t) { return sKV + (t & 1) * Tile::kv_bytes; };  // K, then V at + kv_bytes / 2

  const BlockCoords b = block_coords(p, heads, seqs, Tile::rows);
  const int group = threadIdx.x / 128, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32;
  const std::int64_t head_offset = std::int64_t{b.h} * kMaxHeadDim;
  const bf16* qg = p.q + b.s * p.q_seq + head_offset;
  const bf16* kg = p.k + b.s * p.k_seq + head_offset;
  const bf16* vg = p.v + b.s * p.v_seq + head_offset;
  const int tiles = key_tiles(b.q0, Tile::rows, p.lq, p.lk, p.causal, kKeys);
  const auto load_keys = [&](int t) {
    load_swizzled<kKeys, kThreads>(stage(t), kg, p.k_row, t * kKeys, p.lk, threadIdx.x);
    load_swizzled<kKeys, kThreads>(stage(t) + Tile::kv_bytes / 2, vg, p.v_row, t * kKeys, p.lk, threadIdx.x);
  };
#pragma unroll
  for (int g = 0; g < Tile::groups; ++g)
    load_swizzled<64, kThreads>(sQ + g * Tile::q_bytes, qg, p.q_row, b.q0 + 64 * g, p.lq, threadIdx.x);
  if (tiles > 0) load_keys(0);
  cp_async_commit();

  const int group_row0 = b.q0 + 64 * group, warp_row0 = group_row0 + 16 * warp;
  const int rows[2] = {warp_row0 + lane / 4, warp_row0 + lane / 4 + 8};
  const bool group_active = group_row0 < p.lq;
  float o[kDimTiles][4] = {};
  float m[2] = {-INFINITY, -INFINITY}, l[2] = {0.f, 0.f};
  for (int t = 0; t < tiles; ++t) {
    cp_async_wait_all();
    fence_proxy_async();
    __syncthreads();
    if (t + 1 < tiles) {
      load_keys(t + 1);
      cp_async_commit();
    }
    const int k0 = t * kKeys;
    if (!group_active || (p.causal && k0 > group_row0 + 63)) continue;
    float sc[kKeys / 8][4];
    wg_scores<kKeys>(sc, sQ + group * Tile::q_bytes, stage(t));
    if (tile_masked(p, warp_row0, k0, kKeys))
      online_softmax<true>(sc, m, l, o, p, rows, k0, lane % 4);
    else
      online_softmax<false>(sc, m, l, o, p, rows, k0, lane % 4);
    wg_accumulate_pv<kKeys>(o, sc, stage(t) + Tile::kv_bytes / 2);
  }
  store_rows<true>(o, l, p, rows, b.s, b.h, kMaxHeadDim, lane % 4);
#endif
}

// ---------------------------------------------------------------------------------------
// Warp-specialised kernel: warpgroup 0 is the producer (one thread issues TMA copies of Q and
// of 128-key K and V tiles into two stages, signalled by mbarriers with transaction counts);
// warpgroups 1..kConsumers each compute 64 query rows. TMA writes the same 128-byte swizzle the
// descriptors read, and fills rows past the tensor's end with zeros. A consumer waits for K
// (scores, softmax), then V (P V), then releases the stage to the producer.

// One box (64 channels x rows of one head) of a (channel, head, row, sequence) tensor map to dst.
__device__ __forceinline__ void tma_load(unsigned dst, const CUtensorMap& map, int channel, int head, int row, int seq,
                                         unsigned bar) {
  asm volatile(
      "cp.async.bulk.tensor.4d.shared::cluster.global.tile.mbarrier::complete_tx::bytes [%0], [%1, {%2, %3, %4, %5}], "
      "[%6];\n" ::"r"(dst),
      "l"(reinterpret_cast<std::uint64_t>(&map)), "r"(channel), "r"(head), "r"(row), "r"(seq), "r"(bar)
      : "memory");
}

// A TmaPlan resolved for one call (the kernel's argument). Blocks: the full row blocks of every
// (sequence, head), full_splits key ranges each, then the last, partial row block of every
// (sequence, head), tail_splits ranges: the grid ends with the short work. Rows from
// split_row0 on belong to split row blocks, whose blocks leave partial results: 128
// unnormalised outputs per (pair, row, range) in partial, its max and sum in partial_ml.
struct TmaGrid {
  int heads, seqs, rows, full_row_blocks, full_splits, tail_splits, splits, split_row0;
  std::int64_t blocks;  // row blocks (with their key ranges); a persistent grid has fewer CTAs
  bool share_rows, narrow_last;
  float *partial, *partial_ml;
};

// kStages: K and V tiles in flight. Two consumers sharing rows take alternate tiles, so with
// two stages each would own one and wait for its next load; a third keeps one tile ahead.
template <int kConsumers, int kStages = 2>
struct TmaTiling {
  static constexpr int consumers = kConsumers, keys = 128, rows = 64 * kConsumers, threads = 128 * (kConsumers + 1);
  static constexpr int q_bytes = 64 * kMaxHeadDim * 2;      // one consumer's Q tile
  static constexpr int k_bytes = keys * kMaxHeadDim * 2;    // one K (or V) tile
  static constexpr int stages = kStages;
  static constexpr int bars_offset = kConsumers * q_bytes + stages * 2 * k_bytes;
  // Tiles, the mbarriers (q, then k, v and empty per stage, then Q's and the merge's release),
  // alignment slack.
  static constexpr int smem_bytes = bars_offset + 8 * (3 + 3 * stages) + kAtomBytes;
  static_assert(kConsumers * 128 * kPartialValues * 4 <= stages * 2 * k_bytes, "the merge fits the stages");
};

// A block's share of the work (tma_grid's order): its (sequence, head), first query row, key
// tiles [t_begin, t_end) and, for a block of a split row block, its key range's index.
struct TmaBlock {
  std::int64_t s, pair;
  int h, q0, t_begin, t_end;
  int split;  // -1: the block has all of its rows' keys and stores the normalised output
};
__device__ __forceinline__ TmaBlock tma_block(const FlashParams<bf16>& p, const TmaGrid& g, int tile_keys,
                                              std::int64_t b) {
  const std::int64_t pairs = std::int64_t{g.heads} * g.seqs, per_pair = std::int64_t{g.full_row_blocks} * g.full_splits;
  std::int64_t pair;
  int rb, range, ranges;
  if (b < per_pair * pairs) {
    pair = b / per_pair;
    const int r = static_cast<int>(b % per_pair);
    rb = r / g.full_splits, range = r % g.full_splits, ranges = g.full_splits;
    if (p.causal) rb = g.full_row_blocks - 1 - rb;  // causal: the longest rows first
  } else {
    pair = (b - per_pair * pairs) / g.tail_splits;
    range = static_cast<int>((b - per_pair * pairs) % g.tail_splits), rb = g.full_row_blocks, ranges = g.tail_splits;
  }
  const int q0 = rb * g.rows, tiles = key_tiles(q0, g.rows, p.lq, p.lk, p.causal, tile_keys);
  return {pair / g.heads, pair, static_cast<int>(pair % g.heads), q0, range * tiles / ranges,
          (range + 1) * tiles / ranges, ranges > 1 ? range : -1};
}

// A split block's float32 partial results for one warp's rows g and g + 8: the unnormalised
// output, the rows' max and sum, in the slot of (pair, row, range) that the combine reads.
__device__ __forceinline__ void store_partial(const float (&o)[kDimTiles][4], const float (&m)[2], const float (&l)[2],
                                              const FlashParams<bf16>& p, const TmaGrid& g, const TmaBlock& b,
                                              const int (&rows)[2], int tq) {
#pragma unroll
  for (int i = 0; i < 2; ++i) {
    const float sum = quad_sum(l[i]);
    if (rows[i] >= p.lq) continue;
    const std::int64_t slot = (b.pair * (p.lq - g.split_row0) + rows[i] - g.split_row0) * g.splits + b.split;
    float* out = g.partial + slot * kMaxHeadDim;
#pragma unroll
    for (int nt = 0; nt < kDimTiles; ++nt)
      *reinterpret_cast<float2*>(out + nt * 8 + 2 * tq) = make_float2(o[nt][2 * i], o[nt][2 * i + 1]);
    if (tq == 0) *reinterpret_cast<float2*>(g.partial_ml + 2 * slot) = make_float2(m[i], sum);
  }
}

// One key tile for a consumer warpgroup: S = Q Kᵀ over the tile's first kWidth keys (all of
// them, or a narrow last tile's, which saves the products with its zero-filled rows), softmax,
// then, once V has landed, O += P V.
template <int kWidth, int kTileKeys, class WaitV>
__device__ __forceinline__ void consume_tile(float (&o)[kDimTiles][4], float (&m)[2], float (&l)[2],
                                             const FlashParams<bf16>& p, unsigned sQ, unsigned sK, unsigned sV,
                                             const int (&rows)[2], int warp_row0, int k0, int lane, WaitV wait_v) {
  float sc[kWidth / 8][4];
  wg_scores<kWidth, kTileKeys>(sc, sQ, sK);
  if (tile_masked(p, warp_row0, k0, kWidth))
    online_softmax<true>(sc, m, l, o, p, rows, k0, lane % 4);
  else
    online_softmax<false>(sc, m, l, o, p, rows, k0, lane % 4);
  wait_v();
  wg_accumulate_pv<kWidth, kTileKeys>(o, sc, sV);
}

// Whether a block's consumers share its rows (at most 64 live: each takes a share of the key
// tiles, merged at the end) and how many 64-row Q tiles it loads.
struct TmaRows {
  bool shared;
  int q_tiles;
};
template <class Tile>
__device__ __forceinline__ TmaRows tma_rows(const FlashParams<bf16>& p, const TmaGrid& g, const TmaBlock& b) {
  const bool shared = Tile::consumers > 1 && g.share_rows && min(p.lq - b.q0, g.rows) <= 64;
  return {shared, shared ? 1 : g.rows / 64};
}

// Blocks blockIdx.x, + gridDim.x, ... of the grid's row blocks (one each unless persistent).
// Tiles go through the stages in one sequence across the blocks (n: the CTA's tile count), so
// the producer loads a block's first tiles while the consumers finish the one before; it loads
// a block's Q once the consumers have released the last Q (q_empty), and after a block whose
// consumers merge in the stages' memory, waits for the merge (merged).
template <class Tile>
__global__ void __launch_bounds__(Tile::threads, 1)
    flash_tma_kernel(const __grid_constant__ CUtensorMap q_map, const __grid_constant__ CUtensorMap k_map,
                     const __grid_constant__ CUtensorMap v_map, const FlashParams<bf16> p, const TmaGrid g) {
  wait_for_producer();  // may start before its producer ends (launch_after)
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  constexpr int kKeys = Tile::keys, kStages = Tile::stages;
  extern __shared__ __align__(16) unsigned char smem[];
  const unsigned sQ = first_atom(smem);
  const auto sK = [&](int stage) { return sQ + Tile::consumers * Tile::q_bytes + stage * 2 * Tile::k_bytes; };
  const auto sV = [&](int stage) { return sK(stage) + Tile::k_bytes; };
  const unsigned q_full = sQ + Tile::bars_offset;
  const auto k_full = [&](int stage) { return q_full + 8 * (1 + stage); };
  const auto v_full = [&](int stage) { return q_full + 8 * (1 + kStages + stage); };
  const auto empty = [&](int stage) { return q_full + 8 * (1 + 2 * kStages + stage); };
  const unsigned q_empty = q_full + 8 * (1 + 3 * kStages), merged = q_empty + 8;

  const int wg = threadIdx.x / 128;
  if (threadIdx.x == 0) {
    mbar::init(q_full, 1);
    for (int st = 0; st < kStages; ++st) {
      mbar::init(k_full(st), 1);
      mbar::init(v_full(st), 1);
      mbar::init(empty(st), 4 * Tile::consumers);  // lane 0 of every consumer warp
    }
    mbar::init(q_empty, 4 * Tile::consumers);
    mbar::init(merged, 1);
    asm volatile("fence.mbarrier_init.release.cluster;\n" ::: "memory");
  }
  __syncthreads();

  if (wg == 0) {  // producer
    if constexpr (Tile::consumers > 1) asm volatile("setmaxnreg.dec.sync.aligned.u32 40;\n" ::: "memory");
    if (threadIdx.x != 0) return;
    int n = 0, merges = 0;
    for (std::int64_t item = blockIdx.x, it = 0; item < g.blocks; item += gridDim.x, ++it) {
      const TmaBlock b = tma_block(p, g, kKeys, item);
      const TmaRows r = tma_rows<Tile>(p, g, b);
      if (it > 0) mbar::wait(q_empty, (it - 1) & 1);  // the consumers are done with the last Q
      mbar::expect_bytes(q_full, r.q_tiles * Tile::q_bytes);
      for (int c = 0; c < r.q_tiles; ++c)
        for (int half = 0; half < 2; ++half)
          tma_load(sQ + c * Tile::q_bytes + half * 64 * kRowBytes, q_map, 64 * half, b.h, b.q0 + 64 * c,
                   static_cast<int>(b.s), q_full);
      for (int i = b.t_begin; i < b.t_end; ++i, ++n) {
        const int st = n % kStages, key0 = i * kKeys;
        mbar::wait(empty(st), ((n / kStages) + 1) & 1);  // tile n - kStages released the stage
        mbar::expect_bytes(k_full(st), Tile::k_bytes);
        for (int half = 0; half < 2; ++half)
          tma_load(sK(st) + half * kKeys * kRowBytes, k_map, 64 * half, b.h, key0, static_cast<int>(b.s), k_full(st));
        mbar::expect_bytes(v_full(st), Tile::k_bytes);
        for (int half = 0; half < 2; ++half)
          tma_load(sV(st) + half * kKeys * kRowBytes, v_map, 64 * half, b.h, key0, static_cast<int>(b.s), v_full(st));
      }
      if (r.shared && item + gridDim.x < g.blocks) mbar::wait(merged, merges++ & 1);  // the stages hold the merge
    }
  } else {  // consumer warpgroup wg - 1 (one branch of an if/else: setmaxnreg applies per role)
    if constexpr (Tile::consumers > 1) asm volatile("setmaxnreg.inc.sync.aligned.u32 232;\n" ::: "memory");
    const int group = wg - 1, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32;
    int n = 0;
    for (std::int64_t item = blockIdx.x, it = 0; item < g.blocks; item += gridDim.x, ++it) {
      const TmaBlock b = tma_block(p, g, kKeys, item);
      const TmaRows r = tma_rows<Tile>(p, g, b);
      const int q_tile = r.shared ? 0 : group;
      const int group_row0 = b.q0 + 64 * q_tile, warp_row0 = group_row0 + 16 * warp;
      const int rows[2] = {warp_row0 + lane / 4, warp_row0 + lane / 4 + 8};
      const bool group_active = group_row0 < p.lq && q_tile < r.q_tiles;
      float o[kDimTiles][4] = {};
      float m[2] = {-INFINITY, -INFINITY}, l[2] = {0.f, 0.f};
      mbar::wait(q_full, it & 1);
      for (int i = 0; i < b.t_end - b.t_begin; ++i, ++n) {
        const int st = n % kStages;
        const unsigned parity = (n / kStages) & 1;
        const int k0 = (b.t_begin + i) * kKeys;
        const bool mine = !r.shared || i % Tile::consumers == group;
        const bool compute = mine && group_active && !(p.causal && k0 > group_row0 + 63);
        const auto wait_v = [&] { mbar::wait(v_full(st), parity); };
        // Every consumer waits for every tile, its own or not, before releasing the stage: an
        // early release would count towards the stage's next phase.
        mbar::wait(k_full(st), parity);
        if (!compute) {
          wait_v();
        } else {
          const unsigned q = sQ + q_tile * Tile::q_bytes;
          const int width = g.narrow_last ? p.lk - k0 : kKeys;
          if (width <= 32)
            consume_tile<32, kKeys>(o, m, l, p, q, sK(st), sV(st), rows, warp_row0, k0, lane, wait_v);
          else if (width <= 64)
            consume_tile<64, kKeys>(o, m, l, p, q, sK(st), sV(st), rows, warp_row0, k0, lane, wait_v);
          else
            consume_tile<kKeys, kKeys>(o, m, l, p, q, sK(st), sV(st), rows, warp_row0, k0, lane, wait_v);
        }
        if (lane == 0) mbar::arrive(empty(st));  // this warp is done with the stage (its wgmma waited)
      }
      if (lane == 0) mbar::arrive(q_empty);  // and with Q
      if (r.shared) {
        // Every tile has landed and been read: the stages hold the other consumers' partial
        // results, folded into consumer 0's. The generic accesses are fenced against the
        // producer's next TMA writes to the stages, which wait for `merged`.
        float* stash = reinterpret_cast<float*>(smem + (sK(0) - smem_addr(smem)));
        const int thread = threadIdx.x % 128;
        constexpr int kConsumerThreads = 128 * Tile::consumers;
        named_barrier(1, kConsumerThreads);
        const auto slot = [&](int c) {
          return [stash, thread, c](int v) -> float& { return stash[((c - 1) * kPartialValues + v) * 128 + thread]; };
        };
        if (group > 0) stash_partial(o, m, l, slot(group));
        fence_proxy_async();
        named_barrier(1, kConsumerThreads);
        if (group > 0) continue;
        for (int c = 1; c < Tile::consumers; ++c) fold_partial(o, m, l, slot(c));
        fence_proxy_async();
        named_barrier(2, 128);
        if (thread == 0) mbar::arrive(merged);
      }
      if (q_tile >= r.q_tiles) continue;  // a 64-row block's second consumer, idle without sharing
      if (b.split < 0)
        store_rows<true>(o, l, p, rows, b.s, b.h, kMaxHeadDim, lane % 4);
      else
        store_partial(o, m, l, p, g, b, rows, lane % 4);
    }
  }
#endif
}

// Split row blocks: one warp per query row folds the rows' partial results over the key ranges
// (as online softmax would) and stores the normalised output, rounded to bf16 once.
constexpr int kCombineWarps = 4;
// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void __launch_bounds__(32 * kCombineWarps) combine_splits_kernel(const FlashParams<bf16> p, const TmaGrid g) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const int lane = threadIdx.x % 32;
  const std::int64_t split_rows = p.lq - g.split_row0;
  const std::int64_t r = std::int64_t{blockIdx.x} * kCombineWarps + threadIdx.x / 32;  // (pair, row)
  if (r >= split_rows * g.heads * g.seqs) return;
  const float2* ml = reinterpret_cast<const float2*>(g.partial_ml) + r * g.splits;
  float mx = -INFINITY;
  for (int j = 0; j < g.splits; ++j) mx = fmaxf(mx, ml[j].x);
  const float base = mx == -INFINITY ? 0.f : mx;  // rows without a key stay zero
  float sum = 0.f;
  float4 acc = make_float4(0.f, 0.f, 0.f, 0.f);
  for (int j = 0; j < g.splits; ++j) {
    const float w = exp2_fast(ml[j].x - base);
    const float4 v = reinterpret_cast<const float4*>(g.partial + (r * g.splits + j) * kMaxHeadDim)[lane];
    sum += ml[j].y * w;
    acc.x += v.x * w, acc.y += v.y * w, acc.z += v.z * w, acc.w += v.w * w;
  }
  const float inv = sum > 0.f ? 1.0f / sum : 0.f;
  const std::int64_t pair = r / split_rows, row = g.split_row0 + r % split_rows;
  bf16* out = p.o + pair / g.heads * p.o_seq + row * p.o_row + pair % g.heads * kMaxHeadDim + 4 * lane;
  *reinterpret_cast<uint2*>(out) = make_uint2(pack_bf16(acc.x * inv, acc.y * inv), pack_bf16(acc.z * inv, acc.w * inv));
}

}  // namespace fa

inline bool flash_wgmma_available(const Context& ctx) { return sm90a_available(ctx); }


// One of q, k, v as a (channel, head, row, sequence) tensor of `rows` rows, read in boxes of 64
// channels x box_rows rows of one head with the 128-byte swizzle; rows past the end read as
// zeros. False where the driver cannot describe it (then the cp.async kernel runs).
inline bool head_tensor_map(CUtensorMap& map, const bf16* base, std::int64_t heads, std::int64_t rows,
                            std::int64_t seqs, std::int64_t row_stride, std::int64_t seq_stride, int box_rows) {
  const TensorMapEncoder encode = tensor_map_encoder();
  if (!encode || rows < 1) return false;
  constexpr std::int64_t kElem = sizeof(bf16);
  const cuuint64_t dims[4] = {kMaxHeadDim, static_cast<cuuint64_t>(heads), static_cast<cuuint64_t>(rows),
                              static_cast<cuuint64_t>(seqs)};
  const cuuint64_t strides[3] = {kMaxHeadDim * kElem, static_cast<cuuint64_t>(row_stride * kElem),
                                 static_cast<cuuint64_t>(seqs > 1 ? seq_stride * kElem : rows * row_stride * kElem)};
  const cuuint32_t box[4] = {64, 1, static_cast<cuuint32_t>(box_rows), 1};
  const cuuint32_t unit[4] = {1, 1, 1, 1};
  return encode(&map, CU_TENSOR_MAP_DATA_TYPE_BFLOAT16, 4, const_cast<bf16*>(base), dims, strides, box, unit,
                CU_TENSOR_MAP_INTERLEAVE_NONE, CU_TENSOR_MAP_SWIZZLE_128B, CU_TENSOR_MAP_L2_PROMOTION_L2_256B,
                CU_TENSOR_MAP_FLOAT_OOB_FILL_NONE) == CUDA_SUCCESS;
}

template <class Tile>
void launch_flash_wgmma(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads) {
  const std::int64_t blocks = (p.lq + Tile::rows - 1) / Tile::rows * heads * seqs;
  allow_dynamic_smem<fa::flash_wgmma_kernel<Tile>>(Tile::smem_bytes);
  launch_after(fa::flash_wgmma_kernel<Tile>, static_cast<unsigned>(blocks), Tile::threads, Tile::smem_bytes, ctx,
               p, static_cast<int>(heads), static_cast<int>(seqs));
}

inline std::int64_t tma_partial_bytes(const fa::TmaGrid& g, const FlashParams<bf16>& p) {
  if (g.splits == 1) return 0;
  return std::int64_t{g.heads} * g.seqs * (p.lq - g.split_row0) * g.splits * (kMaxHeadDim + 2) * 4;
}

inline fa::TmaGrid tma_grid(const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads, const TmaPlan& plan) {
  fa::TmaGrid g{};
  g.heads = static_cast<int>(heads), g.seqs = static_cast<int>(seqs), g.rows = plan.rows;
  g.full_row_blocks = p.lq / plan.rows;
  const bool tail = p.lq % plan.rows != 0, split_full = plan.splits > 1 && !plan.tail_only;
  g.full_splits = split_full ? plan.splits : 1;
  g.tail_splits = tail ? plan.splits : 0;
  g.splits = split_full || tail ? plan.splits : 1;
  g.split_row0 = g.splits == 1 ? p.lq : split_full ? 0 : g.full_row_blocks * plan.rows;
  g.share_rows = plan.share_rows, g.narrow_last = plan.narrow_last;
  g.blocks = heads * seqs * (std::int64_t{g.full_row_blocks} * g.full_splits + g.tail_splits);
  return g;
}

inline TmaPlan auto_tma_plan(const Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads) {
  const std::int64_t sms = ctx.info().multiprocessors, pairs = seqs * heads;
  const int tiles = (p.lk + 127) / 128, most = std::min(kMaxSplits, std::max(1, (tiles + 1) / 2));
  const std::int64_t blocks64 = (p.lq + 63) / 64 * pairs;
  TmaPlan plan;
  if (blocks64 <= sms) {  // a wave of 64-row blocks: key ranges fill the idle multiprocessors
    plan.rows = 64;
    plan.splits = static_cast<int>(std::clamp<std::int64_t>(sms / blocks64, 1, most));
  } else {
    // 128-row blocks. Where the full ones fit one wave but the short last row blocks would make
    // a second, those are cut into key ranges that fill the first wave's idle multiprocessors
    // and a short second one (VisDiT 16 x 1027: 128 + 16 blocks). Otherwise the short blocks
    // fill the last wave as they are (measured: cutting them costs the combine and more blocks).
    const std::int64_t full = p.lq / 128 * pairs, tails = p.lq % 128 ? pairs : 0;
    plan.rows = 128;
    plan.tail_only = true;
    plan.splits = tails && full <= sms && full + tails > sms ? most : 1;
    // Several waves (the MST's spatial layers: 800 blocks): one CTA per multiprocessor takes
    // them in turn and overlaps each one's start with the last one's end.
    if (plan.splits == 1 && full + tails > 2 * sms) plan.ctas = static_cast<int>(sms);
  }
  while (plan.splits > 1 && tma_partial_bytes(tma_grid(p, seqs, heads, plan), p) > kSplitPartialBytes) --plan.splits;
  return plan;
}

// The context's buffer for split blocks' partial results, kept for its lifetime: one per
// context, so per stream, whose calls run one after another. A graph capture's first call may
// create it (an allocation that nothing in the graph fills), hence relaxed capture mode.
inline float* split_partial_buffer(Context& ctx) {
  static const std::string name = "attention.split_partials";
  bool created = false;
  if (ctx.has_constant_table(name))  // the common case: no capture-mode calls
    return static_cast<float*>(ctx.constant_table(name, kSplitPartialBytes, &created));
  cudaStreamCaptureMode mode = cudaStreamCaptureModeRelaxed;
  EPONA_CUDA_CHECK(cudaThreadExchangeStreamCaptureMode(&mode));
  void* buffer = nullptr;
  try {
    buffer = ctx.constant_table(name, kSplitPartialBytes, &created);
  } catch (...) {
    (void)cudaThreadExchangeStreamCaptureMode(&mode);
    throw;
  }
  EPONA_CUDA_CHECK(cudaThreadExchangeStreamCaptureMode(&mode));
  return static_cast<float*>(buffer);
}

template <class Tile>
bool launch_flash_tma(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads,
                      const TmaPlan& plan) {
  EPONA_CHECK((plan.rows == 64 || plan.rows == Tile::rows) && plan.splits >= 1 && plan.splits <= kMaxSplits &&
                  plan.ctas >= 0,
              "attention: a TMA plan of ", plan.rows, " rows, ", plan.splits, " key ranges and ", plan.ctas,
              " CTAs is unsupported (64 or ", Tile::rows, " rows, 1..", kMaxSplits, " ranges, CTAs >= 0)");
  CUtensorMap q_map, k_map, v_map;
  if (!head_tensor_map(q_map, p.q, heads, p.lq, seqs, p.q_row, p.q_seq, 64) ||
      !head_tensor_map(k_map, p.k, heads, p.lk, seqs, p.k_row, p.k_seq, Tile::keys) ||
      !head_tensor_map(v_map, p.v, heads, p.lk, seqs, p.v_row, p.v_seq, Tile::keys))
    return false;
  fa::TmaGrid g = tma_grid(p, seqs, heads, plan);
  const std::int64_t bytes = tma_partial_bytes(g, p);
  if (bytes > 0) {
    EPONA_CHECK(bytes <= kSplitPartialBytes, "attention: ", plan.splits, " key ranges need ", bytes,
                " bytes of partial results; the buffer holds ", kSplitPartialBytes);
    g.partial = split_partial_buffer(ctx);
    g.partial_ml = g.partial + bytes / 4 / (kMaxHeadDim + 2) * kMaxHeadDim;
  }
  const std::int64_t grid = plan.ctas > 0 ? std::min<std::int64_t>(g.blocks, plan.ctas) : g.blocks;
  allow_dynamic_smem<fa::flash_tma_kernel<Tile>>(Tile::smem_bytes);
  launch_after(fa::flash_tma_kernel<Tile>, static_cast<unsigned>(grid), Tile::threads, Tile::smem_bytes, ctx,
               q_map, k_map, v_map, p, g);
  if (bytes > 0) {
    const std::int64_t rows = heads * seqs * (p.lq - g.split_row0);
    launch_after(fa::combine_splits_kernel<>, static_cast<unsigned>((rows + fa::kCombineWarps - 1) / fa::kCombineWarps),
                 32 * fa::kCombineWarps, 0, ctx, p, g);
  }
  return true;
}

inline bool launch_flash_wgmma(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads,
                               FlashKernel kernel, const TmaPlan* plan) {
  // Wgmma64: one warpgroup of 64 rows loading its own 64-key tiles by cp.async; 81 KiB, two
  // blocks per multiprocessor. Tma64 / Tma128: a producer warpgroup and one / two consumer
  // warpgroups (64 / 128 rows), 128-key tiles in two stages; 145 / 161 KiB, one block.
  // TmaPlanned: two consumers, three stages (225 KiB), blocks as the plan says.
  constexpr TmaPlan kWhole{64, 1, false, false, false};  // one block per row block, as before the plans
  switch (kernel) {
    case FlashKernel::Tma64: return launch_flash_tma<fa::TmaTiling<1>>(ctx, p, seqs, heads, kWhole);
    case FlashKernel::Tma128:
      return launch_flash_tma<fa::TmaTiling<2>>(ctx, p, seqs, heads, TmaPlan{128, 1, false, false, false});
    case FlashKernel::TmaPlanned:
      return launch_flash_tma<fa::TmaTiling<2, 3>>(ctx, p, seqs, heads,
                                                    plan ? *plan : auto_tma_plan(ctx, p, seqs, heads));
    default: launch_flash_wgmma<fa::WgmmaTiling<1, 64, 2>>(ctx, p, seqs, heads); return true;
  }
}

}  // namespace epona::cuda::detail
