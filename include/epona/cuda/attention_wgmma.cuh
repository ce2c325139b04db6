// epona/cuda/attention_wgmma.cuh — the Hopper (sm_90a) flash-attention kernels for bf16 with
// head dim 128: warpgroup MMA (wgmma), S = Q Kᵀ with both operands in shared memory and O += P V
// with P in registers; online softmax, masking and the output store shared with attention.cuh's
// mma.sync kernels (same float32 accumulation, base-2 softmax and bf16 P). Tiles arrive by
// cp.async from the computing threads, or by the tensor memory accelerator (TMA) from a producer
// warp while consumer warpgroups compute. Included at the end of attention.cuh, which declares
// its entry points; other targets compile empty kernel bodies.
#pragma once

#include <cuda.h>  // CUtensorMap (the encoder itself is fetched from the driver at run time)

#include <cstdint>

#include "epona/cuda/attention.cuh"

namespace epona::cuda::detail {

namespace fa {

// ---------------------------------------------------------------------------------------
// Hopper primitives. Shared-memory tiles of 128 bf16 channels per row are stored as two
// column halves of 64 channels (128 bytes a row), 8-row atoms of 1024 bytes, 16-byte chunk c
// of row r at position c ^ (r % 8) in its row: the canonical 128-byte swizzle that the
// wgmma matrix descriptors name (both for K-major operands, Q and K, and for the N-major V).
// Tiles start at 1024-byte boundaries, so the swizzle phase is the address's own.
constexpr int kRowBytes = 128;        // one row of a column half
constexpr int kAtomBytes = 8 * kRowBytes;

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

// wgmma shared-memory matrix descriptor with the 128-byte swizzle. K-major operands (Q, K):
// `lead` unused, `stride` = 1024 (from one 8-row atom to the next). N-major V: `lead` = the
// distance between the two 64-channel halves, `stride` = 1024 (from one 8-key atom to the next).
__device__ __forceinline__ std::uint64_t smem_desc(unsigned addr, unsigned lead, unsigned stride) {
  return std::uint64_t{(addr & 0x3FFFFu) >> 4} | std::uint64_t{lead >> 4} << 16 | std::uint64_t{stride >> 4} << 32 |
         std::uint64_t{1} << 62;
}

__device__ __forceinline__ void wgmma_fence() { asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory"); }
__device__ __forceinline__ void wgmma_commit() { asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory"); }
__device__ __forceinline__ void wgmma_wait_all() { asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); }
// Makes the shared memory this thread's cp.async wrote visible to the tensor cores' (async) proxy.
__device__ __forceinline__ void fence_proxy_async() { asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory"); }

// Pins accumulator registers at this point of the program: the compiler sees the wgmma asm
// write them when it is issued, so without this it could read them before wgmma_wait_all.
template <int N>
__device__ __forceinline__ void pin(float (&d)[N][4]) {
#pragma unroll
  for (int i = 0; i < N; ++i)
#pragma unroll
    for (int j = 0; j < 4; ++j) asm volatile("" : "+f"(d[i][j])::"memory");
}

// The accumulator operands of a wgmma (d[i][0..3] for each n8 block i), in PTX operand order.
#define EPONA_WGMMA_BLOCK(d, i) "+f"(d[i][0]), "+f"(d[i][1]), "+f"(d[i][2]), "+f"(d[i][3])
#define EPONA_WGMMA_ACCUMULATORS_8(d)                                                                \
  EPONA_WGMMA_BLOCK(d, 0), EPONA_WGMMA_BLOCK(d, 1), EPONA_WGMMA_BLOCK(d, 2), EPONA_WGMMA_BLOCK(d, 3), \
      EPONA_WGMMA_BLOCK(d, 4), EPONA_WGMMA_BLOCK(d, 5), EPONA_WGMMA_BLOCK(d, 6), EPONA_WGMMA_BLOCK(d, 7)
#define EPONA_WGMMA_ACCUMULATORS_16(d)                                                                 \
  EPONA_WGMMA_ACCUMULATORS_8(d), EPONA_WGMMA_BLOCK(d, 8), EPONA_WGMMA_BLOCK(d, 9), EPONA_WGMMA_BLOCK(d, 10), \
      EPONA_WGMMA_BLOCK(d, 11), EPONA_WGMMA_BLOCK(d, 12), EPONA_WGMMA_BLOCK(d, 13), EPONA_WGMMA_BLOCK(d, 14), \
      EPONA_WGMMA_BLOCK(d, 15)

// d (64 x N float32 in the accumulator layout: per warp 16 rows, d[i] = the n8 block i as
// mma.sync's C fragment) (+)= A (64 x 16, shared, descriptor a) B (16 x N, shared, descriptor b).
// accumulate = 0: d = A B.
__device__ __forceinline__ void wgmma_ss(float (&d)[8][4], std::uint64_t a, std::uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %34, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n64k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31}, %32, %33, p, 1, 1, 0, 0;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_8(d)
      : "l"(a), "l"(b), "r"(accumulate));
}

__device__ __forceinline__ void wgmma_ss(float (&d)[16][4], std::uint64_t a, std::uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %66, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n128k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, %32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, %48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}, %64, %65, p, 1, 1, 0, 0;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_16(d)
      : "l"(a), "l"(b), "r"(accumulate));
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
#undef EPONA_WGMMA_ACCUMULATORS_16
#undef EPONA_WGMMA_ACCUMULATORS_8
#undef EPONA_WGMMA_BLOCK

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

template <int kGroups>
__device__ __forceinline__ void wgmma_wait() {
  asm volatile("wgmma.wait_group.sync.aligned %0;\n" ::"n"(kGroups) : "memory");
}
template <int N>
__device__ __forceinline__ void pin(unsigned (&a)[N][4]) {
#pragma unroll
  for (int i = 0; i < N; ++i)
#pragma unroll
    for (int j = 0; j < 4; ++j) asm volatile("" : "+r"(a[i][j])::"memory");
}

// Issues S = Q Kᵀ for the warpgroup's 64 rows and kKeys keys: 8 steps of 16 channels; a step
// moves 32 bytes along the swizzled rows (the hardware applies the swizzle to the full address).
template <int kKeys>
__device__ __forceinline__ void issue_scores(float (&sc)[kKeys / 8][4], unsigned sQ, unsigned sK) {
#pragma unroll
  for (int kk = 0; kk < kMaxHeadDim / 16; ++kk) {
    const unsigned step = (kk % 4) * 32;  // within the 128-byte row of the half kk / 4
    wgmma_ss(sc, smem_desc(sQ + (kk / 4) * 64 * kRowBytes + step, 16, kAtomBytes),
             smem_desc(sK + (kk / 4) * kKeys * kRowBytes + step, 16, kAtomBytes), kk > 0);
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

// Issues O += P V; V's step of 16 keys is two 8-key atoms (2048 bytes) further.
template <int kKeys>
__device__ __forceinline__ void issue_pv(float (&o)[kDimTiles][4], const unsigned (&a)[kKeys / 16][4], unsigned sV) {
#pragma unroll
  for (int kk = 0; kk < kKeys / 16; ++kk)
    wgmma_rs(o, a[kk], smem_desc(sV + kk * 2 * kAtomBytes, kKeys * kRowBytes, kAtomBytes));
}

template <int kKeys>
__device__ __forceinline__ void wg_scores(float (&sc)[kKeys / 8][4], unsigned sQ, unsigned sK) {
  wgmma_fence();
  issue_scores<kKeys>(sc, sQ, sK);
  wgmma_commit();
  wgmma_wait_all();
  pin(sc);
}

template <int kKeys>
__device__ __forceinline__ void wg_accumulate_pv(float (&o)[kDimTiles][4], const float (&sc)[kKeys / 8][4],
                                                 unsigned sV) {
  unsigned a[kKeys / 16][4];
  pack_p<kKeys>(a, sc);
  wgmma_fence();
  issue_pv<kKeys>(o, a, sV);
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
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  constexpr int kKeys = Tile::keys, kThreads = Tile::threads;
  extern __shared__ __align__(16) unsigned char smem[];
  const unsigned sQ = (smem_addr(smem) + kAtomBytes - 1) & ~unsigned{kAtomBytes - 1};
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
namespace mbar {
__device__ __forceinline__ void init(unsigned bar, unsigned count) {
  asm volatile("mbarrier.init.shared::cta.b64 [%0], %1;\n" ::"r"(bar), "r"(count) : "memory");
}
__device__ __forceinline__ void expect_bytes(unsigned bar, unsigned bytes) {
  asm volatile("mbarrier.arrive.expect_tx.shared::cta.b64 _, [%0], %1;\n" ::"r"(bar), "r"(bytes) : "memory");
}
__device__ __forceinline__ void arrive(unsigned bar) {
  asm volatile("mbarrier.arrive.shared::cta.b64 _, [%0];\n" ::"r"(bar) : "memory");
}
// Waits until the phase of parity `parity` has completed (on a fresh barrier, parity 1 has).
__device__ __forceinline__ void wait(unsigned bar, unsigned parity) {
  unsigned done = 0;
  do {
    asm volatile(
        "{\n.reg .pred p;\nmbarrier.try_wait.parity.shared::cta.b64 p, [%1], %2;\nselp.u32 %0, 1, 0, p;\n}\n"
        : "=r"(done)
        : "r"(bar), "r"(parity)
        : "memory");
  } while (!done);
}
}  // namespace mbar

// One box (64 channels x rows of one head) of a (channel, head, row, sequence) tensor map to dst.
__device__ __forceinline__ void tma_load(unsigned dst, const CUtensorMap& map, int channel, int head, int row, int seq,
                                         unsigned bar) {
  asm volatile(
      "cp.async.bulk.tensor.4d.shared::cluster.global.tile.mbarrier::complete_tx::bytes [%0], [%1, {%2, %3, %4, %5}], "
      "[%6];\n" ::"r"(dst),
      "l"(reinterpret_cast<std::uint64_t>(&map)), "r"(channel), "r"(head), "r"(row), "r"(seq), "r"(bar)
      : "memory");
}

template <int kConsumers>
struct TmaTiling {
  static constexpr int consumers = kConsumers, keys = 128, rows = 64 * kConsumers, threads = 128 * (kConsumers + 1);
  static constexpr int q_bytes = 64 * kMaxHeadDim * 2;      // one consumer's Q tile
  static constexpr int k_bytes = keys * kMaxHeadDim * 2;    // one K (or V) tile
  static constexpr int stages = 2;
  static constexpr int bars_offset = kConsumers * q_bytes + stages * 2 * k_bytes;
  // Tiles, the mbarriers (q, then k, v and empty per stage), alignment slack.
  static constexpr int smem_bytes = bars_offset + 8 * (1 + 3 * stages) + kAtomBytes;
};

template <class Tile>
__global__ void __launch_bounds__(Tile::threads, 1)
    flash_tma_kernel(const __grid_constant__ CUtensorMap q_map, const __grid_constant__ CUtensorMap k_map,
                     const __grid_constant__ CUtensorMap v_map, const FlashParams<bf16> p, int heads, int seqs) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  constexpr int kKeys = Tile::keys, kStages = Tile::stages;
  extern __shared__ __align__(16) unsigned char smem[];
  const unsigned sQ = (smem_addr(smem) + kAtomBytes - 1) & ~unsigned{kAtomBytes - 1};
  const auto sK = [&](int stage) { return sQ + Tile::consumers * Tile::q_bytes + stage * 2 * Tile::k_bytes; };
  const auto sV = [&](int stage) { return sK(stage) + Tile::k_bytes; };
  const unsigned q_full = sQ + Tile::bars_offset;
  const auto k_full = [&](int stage) { return q_full + 8 * (1 + stage); };
  const auto v_full = [&](int stage) { return q_full + 8 * (1 + kStages + stage); };
  const auto empty = [&](int stage) { return q_full + 8 * (1 + 2 * kStages + stage); };

  const BlockCoords b = block_coords(p, heads, seqs, Tile::rows);
  const int tiles = key_tiles(b.q0, Tile::rows, p.lq, p.lk, p.causal, kKeys);
  const int wg = threadIdx.x / 128;
  if (threadIdx.x == 0) {
    mbar::init(q_full, 1);
    for (int st = 0; st < kStages; ++st) {
      mbar::init(k_full(st), 1);
      mbar::init(v_full(st), 1);
      mbar::init(empty(st), 4 * Tile::consumers);  // lane 0 of every consumer warp
    }
    asm volatile("fence.mbarrier_init.release.cluster;\n" ::: "memory");
  }
  __syncthreads();

  if (wg == 0) {  // producer
    if constexpr (Tile::consumers > 1) asm volatile("setmaxnreg.dec.sync.aligned.u32 40;\n" ::: "memory");
    if (threadIdx.x != 0) return;
    mbar::expect_bytes(q_full, Tile::consumers * Tile::q_bytes);
    for (int g = 0; g < Tile::consumers; ++g)
      for (int half = 0; half < 2; ++half)
        tma_load(sQ + g * Tile::q_bytes + half * 64 * kRowBytes, q_map, 64 * half, b.h, b.q0 + 64 * g,
                 static_cast<int>(b.s), q_full);
    for (int t = 0; t < tiles; ++t) {
      const int st = t % kStages;
      mbar::wait(empty(st), ((t / kStages) + 1) & 1);  // tile t - kStages released the stage
      mbar::expect_bytes(k_full(st), Tile::k_bytes);
      for (int half = 0; half < 2; ++half)
        tma_load(sK(st) + half * kKeys * kRowBytes, k_map, 64 * half, b.h, t * kKeys, static_cast<int>(b.s), k_full(st));
      mbar::expect_bytes(v_full(st), Tile::k_bytes);
      for (int half = 0; half < 2; ++half)
        tma_load(sV(st) + half * kKeys * kRowBytes, v_map, 64 * half, b.h, t * kKeys, static_cast<int>(b.s), v_full(st));
    }
  } else {  // consumer warpgroup wg - 1 (one branch of an if/else: setmaxnreg applies per role)
    if constexpr (Tile::consumers > 1) asm volatile("setmaxnreg.inc.sync.aligned.u32 232;\n" ::: "memory");
    const int group = wg - 1, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32;
    const int group_row0 = b.q0 + 64 * group, warp_row0 = group_row0 + 16 * warp;
    const int rows[2] = {warp_row0 + lane / 4, warp_row0 + lane / 4 + 8};
    const bool group_active = group_row0 < p.lq;
    float o[kDimTiles][4] = {};
    float m[2] = {-INFINITY, -INFINITY}, l[2] = {0.f, 0.f};
    mbar::wait(q_full, 0);
    for (int t = 0; t < tiles; ++t) {
      const int st = t % kStages;
      const unsigned parity = (t / kStages) & 1;
      const int k0 = t * kKeys;
      const bool compute = group_active && !(p.causal && k0 > group_row0 + 63);
      float sc[kKeys / 8][4];
      mbar::wait(k_full(st), parity);
      if (compute) {
        wg_scores<kKeys>(sc, sQ + group * Tile::q_bytes, sK(st));
        if (tile_masked(p, warp_row0, k0, kKeys))
          online_softmax<true>(sc, m, l, o, p, rows, k0, lane % 4);
        else
          online_softmax<false>(sc, m, l, o, p, rows, k0, lane % 4);
      }
      mbar::wait(v_full(st), parity);
      if (compute) wg_accumulate_pv<kKeys>(o, sc, sV(st));
      if (lane == 0) mbar::arrive(empty(st));  // this warp is done with the stage (its wgmma waited)
    }
    store_rows<true>(o, l, p, rows, b.s, b.h, kMaxHeadDim, lane % 4);
  }
#endif
}

// Present only in sm_90a code: its static shared memory tells the host that this build has
// the wgmma kernels (the same binary may run on a GPU whose code was built without them).
constexpr int kWgmmaMarkerWords = 12;
__global__ void wgmma_marker_kernel(int* flag) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  __shared__ int present[kWgmmaMarkerWords];
  present[threadIdx.x % kWgmmaMarkerWords] = 1;
  __syncthreads();
  if (flag) *flag = present[0];
#endif
}
}  // namespace fa

inline bool flash_wgmma_available(const Context& ctx) {
  if (ctx.info().major != 9 || ctx.info().minor != 0) return false;  // sm_90a code runs on 9.0 only
  static const bool built = [] {
    cudaFuncAttributes a{};
    if (cudaFuncGetAttributes(&a, fa::wgmma_marker_kernel) != cudaSuccess) {
      (void)cudaGetLastError();
      return false;
    }
    return a.sharedSizeBytes == fa::kWgmmaMarkerWords * sizeof(int);
  }();
  return built;
}

// The driver's cuTensorMapEncodeTiled, fetched once through the runtime (no libcuda link); null
// where the driver lacks it.
using TensorMapEncoder = CUresult (*)(CUtensorMap*, CUtensorMapDataType, cuuint32_t, void*, const cuuint64_t*,
                                      const cuuint64_t*, const cuuint32_t*, const cuuint32_t*, CUtensorMapInterleave,
                                      CUtensorMapSwizzle, CUtensorMapL2promotion, CUtensorMapFloatOOBfill);
inline TensorMapEncoder tensor_map_encoder() {
  static const TensorMapEncoder encode = [] {
    void* fn = nullptr;
    cudaDriverEntryPointQueryResult found{};
    if (cudaGetDriverEntryPointByVersion("cuTensorMapEncodeTiled", &fn, 12000, cudaEnableDefault, &found) !=
            cudaSuccess ||
        found != cudaDriverEntryPointSuccess) {
      (void)cudaGetLastError();
      return TensorMapEncoder{};
    }
    return reinterpret_cast<TensorMapEncoder>(fn);
  }();
  return encode;
}

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
  fa::flash_wgmma_kernel<Tile><<<static_cast<unsigned>(blocks), Tile::threads, Tile::smem_bytes, ctx.stream()>>>(
      p, static_cast<int>(heads), static_cast<int>(seqs));
}

template <class Tile>
bool launch_flash_tma(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads) {
  CUtensorMap q_map, k_map, v_map;
  if (!head_tensor_map(q_map, p.q, heads, p.lq, seqs, p.q_row, p.q_seq, 64) ||
      !head_tensor_map(k_map, p.k, heads, p.lk, seqs, p.k_row, p.k_seq, Tile::keys) ||
      !head_tensor_map(v_map, p.v, heads, p.lk, seqs, p.v_row, p.v_seq, Tile::keys))
    return false;
  const std::int64_t blocks = (p.lq + Tile::rows - 1) / Tile::rows * heads * seqs;
  allow_dynamic_smem<fa::flash_tma_kernel<Tile>>(Tile::smem_bytes);
  fa::flash_tma_kernel<Tile><<<static_cast<unsigned>(blocks), Tile::threads, Tile::smem_bytes, ctx.stream()>>>(
      q_map, k_map, v_map, p, static_cast<int>(heads), static_cast<int>(seqs));
  return true;
}

inline bool launch_flash_wgmma(Context& ctx, const FlashParams<bf16>& p, std::int64_t seqs, std::int64_t heads,
                               FlashKernel kernel) {
  // Wgmma64: one warpgroup of 64 rows loading its own 64-key tiles by cp.async; 81 KiB, two
  // blocks per multiprocessor. Tma64 / Tma128: a producer warpgroup and one / two consumer
  // warpgroups (64 / 128 rows), 128-key tiles in two stages; 145 / 161 KiB, one block.
  switch (kernel) {
    case FlashKernel::Tma64: return launch_flash_tma<fa::TmaTiling<1>>(ctx, p, seqs, heads);
    case FlashKernel::Tma128: return launch_flash_tma<fa::TmaTiling<2>>(ctx, p, seqs, heads);
    default: launch_flash_wgmma<fa::WgmmaTiling<1, 64, 2>>(ctx, p, seqs, heads); return true;
  }
}

}  // namespace epona::cuda::detail
