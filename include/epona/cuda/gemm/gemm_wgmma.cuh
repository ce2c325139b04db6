// epona/cuda/gemm/gemm_wgmma.cuh — our own Hopper (sm_90a) bf16 GEMM, y = act(x · wᵀ + b), for the
// products whose epilogue cuBLASLt cannot fuse: the MST's MLP (c_fc, 5150 x 8192 x 2048) is
// followed by the exact (erf) GELU, which cuBLASLt lacks, so there it costs one more pass over
// 84 MB (41.8 µs of 291 per layer). Here the GELU is applied to the accumulators before the
// one store.
//
// Warp-specialised and persistent: one block per multiprocessor walks output tiles of 128 x 256;
// one producer thread streams 128 x 64 tiles of x and 256 x 64 tiles of w through three
// shared-memory stages by TMA (128-byte swizzle, rows past the end zero-filled); two consumer
// warpgroups each multiply 64 of the tile's rows by all 256 columns (wgmma m64n256k16, float32
// accumulators) and stage their rounded rows in shared memory; three epilogue warps apply the
// activation there and store the tile by TMA while the consumers compute the next tile (erff
// on the consumers' critical path cost as much as the tile's stores: 282 against 236 µs for
// the MST's c_fc on the H200).
//
// Numerics: exactly the cuBLASLt path's. The float32 sum plus bias is rounded to bf16 (what
// cuBLASLt stores), the activation is computed in float32 on that bf16 value and rounded
// again (what the activation pass does), so y is bit-identical to "cuBLASLt, then the pass"
// up to the products' summation order.
#pragma once

#include <cuda.h>

#include <algorithm>
#include <atomic>
#include <cstdint>

#include "epona/core/env.hpp"
#include "epona/cuda/pointwise/activation.cuh"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/ptx/mma.cuh"
#include "epona/cuda/ptx/wgmma.cuh"

namespace epona::cuda::detail {

namespace hg {

constexpr int kRows = 128, kCols = 256, kDepth = 64;  // output tile and the k-slice of a stage
constexpr int kStages = 3, kConsumers = 2, kThreads = 128 * (1 + kConsumers);
constexpr int kXBytes = kRows * kDepth * 2, kWBytes = kCols * kDepth * 2, kStageBytes = kXBytes + kWBytes;
static_assert(kDepth * 2 == kRowBytes, "a stage row (and an output box row) is one swizzled row");
constexpr int kBoxBytes = 64 * kRowBytes;     // an output box: 64 rows x 64 columns
constexpr int kOutBytes = kRows * kCols * 2;  // the output tile, as 2 x 4 boxes (row half, columns / 64)
constexpr int kEpilogueThreads = 96;          // warps 1-3 of the producer warpgroup
constexpr int kOutOffset = kStages * kStageBytes, kBarsOffset = kOutOffset + kOutBytes;
constexpr int kSmemBytes = kBarsOffset + 8 * (2 * kStages + 2) + kAtomBytes;  // + slack for first_atom

struct Args {
  const bf16* bias;  // (N) or null
  int M, N, K, row_tiles, col_tiles;
};

// The epilogue: the float32 sum (+ bias) rounded to bf16 as cuBLASLt stores it; then, unless
// Op is Identity, Op of that bf16 value in float32, rounded again (as the activation pass).
template <class Op>
struct RoundedThen {
  Op op;
  static constexpr bool activates = !std::is_same_v<Op, Identity>;
  __device__ __forceinline__ static unsigned round_pair(float lo, float hi) {
    return static_cast<unsigned>(from_f32<bf16>(lo).bits) | static_cast<unsigned>(from_f32<bf16>(hi).bits) << 16;
  }
  __device__ __forceinline__ unsigned activate_pair(unsigned w) const {
    bf16 lo, hi;
    lo.bits = static_cast<std::uint16_t>(w), hi.bits = static_cast<std::uint16_t>(w >> 16);
    return round_pair(op(to_f32(lo)), op(to_f32(hi)));
  }
};

// A consumer warp's 16 rows x 256 columns of the tile (accumulator layout: rows r and r + 8,
// columns 8 i + c and + 1), plus bias and rounded, into its 64-row half of the output tile in
// shared memory, as the four 128-byte-swizzled boxes the TMA store reads. Conflict-free: a
// warp's 8 rows of one column pack land in 8 different 16-byte chunks.
template <class Epi>
__device__ __forceinline__ void stage_rows(const float (&acc)[kCols / 8][4], const Args& g, unsigned out, int r, int c,
                                           int n0) {
#pragma unroll
  for (int i = 0; i < kCols / 8; ++i) {
    const int col = 8 * i + c;
    float b0 = 0, b1 = 0;
    if (g.bias && n0 + col < g.N) b0 = to_f32(g.bias[n0 + col]), b1 = to_f32(g.bias[n0 + col + 1]);
#pragma unroll
    for (int h = 0; h < 2; ++h) {
      const int row = r + 8 * h;
      const unsigned at = out + (i / 8) * kBoxBytes + row * kRowBytes + (((i % 8) ^ (row % 8)) << 4) + c * 2;
      asm volatile("st.shared.b32 [%0], %1;\n" ::"r"(at), "r"(Epi::round_pair(acc[i][2 * h] + b0, acc[i][2 * h + 1] + b1))
                   : "memory");
    }
  }
}

// The activation over the whole staged tile, in place, by the epilogue warps (16-byte chunks).
template <class Epi>
__device__ __forceinline__ void activate_tile(const Epi& epi, unsigned out, int thread) {
  for (int chunk = thread; chunk < kOutBytes / 16; chunk += kEpilogueThreads) {
    const unsigned at = out + 16 * chunk;
    unsigned v[4];
    asm volatile("ld.shared.v4.b32 {%0, %1, %2, %3}, [%4];\n" : "=r"(v[0]), "=r"(v[1]), "=r"(v[2]), "=r"(v[3]) : "r"(at));
#pragma unroll
    for (int k = 0; k < 4; ++k) v[k] = epi.activate_pair(v[k]);
    asm volatile("st.shared.v4.b32 [%0], {%1, %2, %3, %4};\n" ::"r"(at), "r"(v[0]), "r"(v[1]), "r"(v[2]), "r"(v[3])
                 : "memory");
  }
}

// Roles: warp 0's first thread loads stages by TMA; warps 1-3 (the epilogue) activate each
// finished tile in shared memory and store it by TMA while the consumers (warpgroups 1 and 2)
// compute the next; consumer c multiplies rows 64 c .. + 64 of each tile by all its columns.
// Barriers: full/empty per stage (TMA -> consumers -> TMA), out_full (the 256 consumer threads
// staged the tile) and out_empty (the epilogue's store has read it).
template <class Epi>
__global__ void __launch_bounds__(kThreads, 1)
    gemm_kernel(const __grid_constant__ CUtensorMap x_map, const __grid_constant__ CUtensorMap w_map,
                const __grid_constant__ CUtensorMap y_map, const Args g, Epi epi) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  extern __shared__ __align__(16) unsigned char smem[];
  const unsigned base = first_atom(smem);
  const auto sx = [&](int st) { return base + st * kStageBytes; };
  const auto sw = [&](int st) { return sx(st) + kXBytes; };
  const auto full = [&](int st) { return base + kBarsOffset + 8 * st; };
  const auto empty = [&](int st) { return base + kBarsOffset + 8 * (kStages + st); };
  const unsigned out = base + kOutOffset, out_full = base + kBarsOffset + 16 * kStages, out_empty = out_full + 8;
  if (threadIdx.x == 0) {
    for (int st = 0; st < kStages; ++st) {
      mbar::init(full(st), 1);
      mbar::init(empty(st), 4 * kConsumers);  // lane 0 of every consumer warp
    }
    mbar::init(out_full, 128 * kConsumers);
    mbar::init(out_empty, 1);
    asm volatile("fence.mbarrier_init.release.cluster;\n" ::: "memory");
  }
  __syncthreads();
  const int k_tiles = (g.K + kDepth - 1) / kDepth, tiles = g.row_tiles * g.col_tiles;
  const int wg = threadIdx.x / 128;
  // Tiles go down the rows first: the blocks of a wave share a few column tiles of w.
  const auto origin = [&](int t, int& m0, int& n0) { m0 = t % g.row_tiles * kRows, n0 = t / g.row_tiles * kCols; };
  if (wg == 0) {
    asm volatile("setmaxnreg.dec.sync.aligned.u32 56;\n" ::: "memory");
    if (threadIdx.x == 0) {  // producer
      int it = 0;
      for (int t = blockIdx.x; t < tiles; t += gridDim.x) {
        int m0, n0;
        origin(t, m0, n0);
        for (int kt = 0; kt < k_tiles; ++kt, ++it) {
          const int st = it % kStages;
          mbar::wait(empty(st), (it / kStages + 1) & 1);  // the slice kStages earlier was consumed
          mbar::expect_bytes(full(st), kStageBytes);
          tma_load_2d(sx(st), x_map, kt * kDepth, m0, full(st));
          tma_load_2d(sw(st), w_map, kt * kDepth, n0, full(st));
        }
      }
    } else if (threadIdx.x >= 32) {  // epilogue
      const int e = threadIdx.x - 32;
      int n = 0;
      for (int t = blockIdx.x; t < tiles; t += gridDim.x, ++n) {
        int m0, n0;
        origin(t, m0, n0);
        // One thread polls the barrier; the others sleep in the named barrier (96 threads
        // polling took shared-memory cycles from the consumers' wgmma: 258 against 236 µs).
        if (e == 0) mbar::wait(out_full, n & 1);
        named_barrier(1, kEpilogueThreads);
        if constexpr (Epi::activates) {
          activate_tile(epi, out, e);
          fence_proxy_async();  // likewise the activation's writes
        }
        named_barrier(1, kEpilogueThreads);
        if (e == 0) {
          for (int half = 0; half < 2; ++half)
            for (int b = 0; b < kCols / 64; ++b)
              tma_store_2d(y_map, n0 + 64 * b, m0 + 64 * half, out + (4 * half + b) * kBoxBytes);
          bulk_commit();
          bulk_wait_all<true>();
          mbar::arrive(out_empty);
        }
      }
      if (e == 0) bulk_wait_all<false>();
    }
  } else {  // consumer warpgroup wg - 1
    asm volatile("setmaxnreg.inc.sync.aligned.u32 224;\n" ::: "memory");
    const int c = wg - 1, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32;
    int it = 0, n = 0;
    for (int t = blockIdx.x; t < tiles; t += gridDim.x, ++n) {
      int m0, n0;
      origin(t, m0, n0);
      float acc[kCols / 8][4];
      for (int kt = 0; kt < k_tiles; ++kt, ++it) {
        const int st = it % kStages;
        mbar::wait(full(st), (it / kStages) & 1);
        wgmma_fence();
#pragma unroll
        for (int k = 0; k < kDepth / 16; ++k)  // 16 channels = 32 bytes along the swizzled rows
          wgmma_ss(acc, smem_desc(sx(st) + c * 64 * kRowBytes + 32 * k, 16, kAtomBytes),
                   smem_desc(sw(st) + 32 * k, 16, kAtomBytes), kt > 0 || k > 0);
        wgmma_commit();
        wgmma_wait<1>();  // the previous slice's products are done: release its stage
        if (kt > 0 && lane == 0) mbar::arrive(empty((it - 1) % kStages));
      }
      wgmma_wait<0>();
      pin(acc);
      if (lane == 0) mbar::arrive(empty((it - 1) % kStages));
      mbar::wait(out_empty, (n + 1) & 1);  // the previous tile's store has read the staging tile
      stage_rows<Epi>(acc, g, out + c * 4 * kBoxBytes, 16 * warp + lane / 4, 2 * (lane % 4), n0);
      fence_proxy_async();  // these generic-proxy writes, before the TMA store reads them
      mbar::arrive(out_full);
    }
  }
#else
  (void)g, (void)epi;
#endif
}

// A row-major (rows, cols) bf16 matrix, rows ld elements apart, in boxes of 64 columns x
// box_rows rows with the 128-byte swizzle: loads read out-of-range elements as zeros, stores
// skip them.
inline bool matrix_tensor_map(CUtensorMap& map, const bf16* base, std::int64_t rows, std::int64_t cols,
                              std::int64_t ld, int box_rows) {
  const TensorMapEncoder encode = tensor_map_encoder();
  if (!encode) return false;
  const cuuint64_t dims[2] = {static_cast<cuuint64_t>(cols), static_cast<cuuint64_t>(rows)};
  const cuuint64_t strides[1] = {static_cast<cuuint64_t>(ld * 2)};
  const cuuint32_t box[2] = {kDepth, static_cast<cuuint32_t>(box_rows)};
  const cuuint32_t unit[2] = {1, 1};
  return encode(&map, CU_TENSOR_MAP_DATA_TYPE_BFLOAT16, 2, const_cast<bf16*>(base), dims, strides, box, unit,
                CU_TENSOR_MAP_INTERLEAVE_NONE, CU_TENSOR_MAP_SWIZZLE_128B, CU_TENSOR_MAP_L2_PROMOTION_L2_256B,
                CU_TENSOR_MAP_FLOAT_OOB_FILL_NONE) == CUDA_SUCCESS;
}

}  // namespace hg

// EPONA_CUDA_OWN_GEMM=1 sends the bf16 erf-GELU products to this kernel. Off by default: on the
// H200 it does the MST's c_fc in 261-270 µs against 270 for cuBLASLt + the pass, and the MST as
// a whole measured the same either way (22.17 / 22.15 ms against 22.17 / 22.14); without an
// activation it runs at 670 TFLOP/s where cuBLASLt reaches 720-770.

// Where the kernel replaces cuBLASLt (+ a pass): products of at least a tile of rows and a
// stage of depth (smaller ones keep their measured paths), with the switch on.
inline bool own_gemm_wins(const Context& ctx, std::int64_t M, std::int64_t K) {
  return ctx.policy().own_gemm && M >= hg::kRows && K >= hg::kDepth;
}

// Whether the kernel can take this product: bf16 rows whose strides and starts TMA and the
// paired stores accept (16-byte aligned, N even), 32-bit extents, an sm_90a GPU and build.
inline bool own_gemm_fits(const Context& ctx, const bf16* x, std::int64_t ldx, const bf16* w, const bf16* bias,
                          const bf16* y, std::int64_t ldy, std::int64_t M, std::int64_t N, std::int64_t K) {
  const auto limit = std::int64_t{1} << 31;
  return M > 0 && M < limit && N < limit && K < limit && N % 2 == 0 && ldx % 8 == 0 && K % 8 == 0 && ldy % 8 == 0 &&
         aligned16(x) && aligned16(w) && aligned16(y) && reinterpret_cast<std::uintptr_t>(bias) % 4 == 0 &&
         sm90a_available(ctx);
}

// y = Op(round(x · wᵀ + bias)) by the kernel above; false (nothing launched) where it does
// not fit or the driver cannot describe the operands.
template <class Op>
bool own_gemm(Context& ctx, const bf16* x, std::int64_t ldx, const bf16* w, const bf16* bias, bf16* y,
              std::int64_t ldy, std::int64_t M, std::int64_t N, std::int64_t K, Op op) {
  if (!own_gemm_fits(ctx, x, ldx, w, bias, y, ldy, M, N, K)) return false;
  CUtensorMap x_map, w_map, y_map;
  if (!hg::matrix_tensor_map(x_map, x, M, K, ldx, hg::kRows) || !hg::matrix_tensor_map(w_map, w, N, K, K, hg::kCols) ||
      !hg::matrix_tensor_map(y_map, y, M, N, ldy, 64))
    return false;
  hg::Args g{bias, static_cast<int>(M), static_cast<int>(N), static_cast<int>(K),
             static_cast<int>((M + hg::kRows - 1) / hg::kRows), static_cast<int>((N + hg::kCols - 1) / hg::kCols)};
  const std::int64_t tiles = std::int64_t{g.row_tiles} * g.col_tiles;
  const auto blocks = static_cast<unsigned>(std::min<std::int64_t>(tiles, ctx.info().multiprocessors));
  using Epi = hg::RoundedThen<Op>;
  allow_dynamic_smem<hg::gemm_kernel<Epi>>(hg::kSmemBytes);
  hg::gemm_kernel<Epi><<<blocks, hg::kThreads, hg::kSmemBytes, ctx.stream()>>>(x_map, w_map, y_map, g, Epi{op});
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

}  // namespace epona::cuda::detail
