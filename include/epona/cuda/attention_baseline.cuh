// epona/cuda/attention_baseline.cuh — TEMPORARY: the bf16 flash kernel as it was before issue #5
// (4 warps x 16 rows, one K and one V buffer, two barriers per key tile), kept only so that
// the benchmark and the test can measure it side by side with the new kernels. To be deleted.
#pragma once

#include <cmath>
#include <cstdint>

#include "epona/cuda/attention.cuh"

namespace epona::cuda::attention_baseline {

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
// bf16 tensor-core kernel. A block of 4 warps owns 64 query rows (16 per warp) of one
// (sequence, head); K and V tiles of 64 keys stream through shared memory (V(t) loads while
// S = Q K(t)ᵀ is computed, K(t+1) while O += P V(t) is), rows padded by 16 bytes so that
// ldmatrix is free of bank conflicts. kExactDim: head_dim == 128 with 16-byte aligned rows
// (cp.async loads); otherwise any head_dim <= 128, zero-padded, with guarded loads.
namespace fa {
constexpr int kRows = 64, kKeys = 64, kWarps = 4, kThreads = kWarps * 32;
constexpr int kStride = kMaxHeadDim + 8;  // shared-memory row stride, in bf16 elements
constexpr int kSmemBytes = (kRows + 2 * kKeys) * kStride * 2;

__device__ __forceinline__ unsigned smem_addr(const void* p) {
  return static_cast<unsigned>(__cvta_generic_to_shared(p));
}
__device__ __forceinline__ void cp_async_16(void* dst, const void* src) {
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" ::"r"(smem_addr(dst)), "l"(src));
}
__device__ __forceinline__ void cp_async_commit() { asm volatile("cp.async.commit_group;\n" ::); }
__device__ __forceinline__ void cp_async_wait_all() { asm volatile("cp.async.wait_group 0;\n" ::: "memory"); }

__device__ __forceinline__ void ldmatrix_x4(unsigned (&r)[4], const void* p) {
  asm volatile("ldmatrix.sync.aligned.m8n8.x4.shared.b16 {%0, %1, %2, %3}, [%4];\n"
               : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
               : "r"(smem_addr(p)));
}
__device__ __forceinline__ void ldmatrix_x4_trans(unsigned (&r)[4], const void* p) {
  asm volatile("ldmatrix.sync.aligned.m8n8.x4.trans.shared.b16 {%0, %1, %2, %3}, [%4];\n"
               : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
               : "r"(smem_addr(p)));
}
// d (16x8, f32) += a (16x16 bf16, row) * b (16x8 bf16, col).
__device__ __forceinline__ void mma_bf16(float (&d)[4], const unsigned (&a)[4], unsigned b0, unsigned b1) {
  asm volatile(
      "mma.sync.aligned.m16n8k16.row.col.f32.bf16.bf16.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, {%8, %9}, "
      "{%0, %1, %2, %3};\n"
      : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3])
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}
__device__ __forceinline__ unsigned pack_bf16(float lo, float hi) {
  const __nv_bfloat162 v = __floats2bfloat162_rn(lo, hi);
  return *reinterpret_cast<const unsigned*>(&v);
}

// Rows [row0, row0 + 64) of one head (row i at src + i * stride) into shared memory; rows
// past `valid` and channels past head_dim become zeros.
template <bool kExactDim>
__device__ __forceinline__ void load_tile(bf16* dst, const bf16* src, std::int64_t stride, int row0, int valid,
                                          int head_dim) {
  if constexpr (kExactDim) {
    constexpr int kChunks = kMaxHeadDim / 8;  // 16-byte chunks per row
    for (int c = threadIdx.x; c < kRows * kChunks; c += kThreads) {
      const int r = c / kChunks, col = (c % kChunks) * 8;
      bf16* d = dst + r * kStride + col;
      if (row0 + r < valid)
        cp_async_16(d, src + (row0 + r) * stride + col);
      else
        *reinterpret_cast<uint4*>(d) = make_uint4(0, 0, 0, 0);
    }
  } else {
    for (int e = threadIdx.x; e < kRows * kMaxHeadDim; e += kThreads) {
      const int r = e / kMaxHeadDim, col = e % kMaxHeadDim;
      bf16 val{};
      if (row0 + r < valid && col < head_dim) val = src[(row0 + r) * stride + col];
      dst[r * kStride + col] = val;
    }
  }
}

constexpr int kDimTiles = kMaxHeadDim / 8, kKeyTiles = kKeys / 8;

// S = Q K(t)ᵀ for one warp's 16 query rows: 16 x 64 in 8 accumulator tiles.
template <bool kExactDim>
__device__ __forceinline__ void warp_scores(float (&sc)[kKeyTiles][4], const bf16* sQ, const bf16* sK, int warp,
                                            int lane, int D) {
#pragma unroll
  for (int kk = 0; kk < kMaxHeadDim / 16; ++kk) {
    if (!kExactDim && kk * 16 >= D) break;
    unsigned a[4];
    ldmatrix_x4(a, sQ + (warp * 16 + (lane & 15)) * kStride + kk * 16 + (lane >> 4) * 8);
#pragma unroll
    for (int n2 = 0; n2 < kKeys / 16; ++n2) {
      unsigned b[4];
      ldmatrix_x4(b, sK + (n2 * 16 + (lane & 7) + ((lane >> 4) << 3)) * kStride + kk * 16 + ((lane >> 3) & 1) * 8);
      mma_bf16(sc[2 * n2], a, b[0], b[1]);
      mma_bf16(sc[2 * n2 + 1], a, b[2], b[3]);
    }
  }
}

// Scales (base 2) and masks the scores of key tile k0 in place, then folds them into the
// running max m and sum l of this thread's two rows, leaving P = exp2(S - m) in sc and the
// output accumulators rescaled to the new max. kMasked: the tile has keys past lk, past the
// causal diagonal of some row, or an additive mask (most tiles have none: no per-score tests).
template <bool kMasked>
__device__ __forceinline__ void online_softmax(float (&sc)[kKeyTiles][4], float (&m)[2], float (&l)[2],
                                               float (&o)[kDimTiles][4], const FlashParams<bf16>& p,
                                               const int (&rows)[2], int k0, int tq) {
#pragma unroll
  for (int i = 0; i < 2; ++i) {
    float mx = -INFINITY;
#pragma unroll
    for (int nt = 0; nt < kKeyTiles; ++nt)
#pragma unroll
      for (int e = 0; e < 2; ++e) {
        float x = sc[nt][2 * i + e] * p.scale;
        if constexpr (kMasked) {
          const int col = k0 + nt * 8 + 2 * tq + e;
          if (p.mask && rows[i] < p.lq && col < p.lk)
            x += p.mask[std::int64_t{rows[i]} * p.lk + col] * 1.4426950408889634f;
          if (col >= p.lk || (p.causal && col > rows[i])) x = -INFINITY;
        }
        sc[nt][2 * i + e] = x;
        mx = fmaxf(mx, x);
      }
    mx = fmaxf(mx, __shfl_xor_sync(0xffffffffu, mx, 1));  // the row's four threads
    mx = fmaxf(mx, __shfl_xor_sync(0xffffffffu, mx, 2));
    const float m_new = fmaxf(m[i], mx);
    const float base = m_new == -INFINITY ? 0.f : m_new;  // a row masked so far stays all zero
    const float alpha = exp2f(m[i] - base);
    m[i] = m_new;
    float sum = 0;
#pragma unroll
    for (int nt = 0; nt < kKeyTiles; ++nt)
#pragma unroll
      for (int e = 0; e < 2; ++e) {
        const float pr = exp2f(sc[nt][2 * i + e] - base);
        sc[nt][2 * i + e] = pr;
        sum += pr;
      }
    l[i] = l[i] * alpha + sum;  // this thread's share of the row; reduced over the quad at the end
#pragma unroll
    for (int nt = 0; nt < kDimTiles; ++nt) {
      o[nt][2 * i] *= alpha;
      o[nt][2 * i + 1] *= alpha;
    }
  }
}

// O += P V(t): the S accumulators of two adjacent key tiles form one A fragment of P.
template <bool kExactDim>
__device__ __forceinline__ void warp_pv(float (&o)[kDimTiles][4], const float (&sc)[kKeyTiles][4], const bf16* sV,
                                        int lane, int D) {
#pragma unroll
  for (int kk = 0; kk < kKeys / 16; ++kk) {
    const unsigned a[4] = {pack_bf16(sc[2 * kk][0], sc[2 * kk][1]), pack_bf16(sc[2 * kk][2], sc[2 * kk][3]),
                           pack_bf16(sc[2 * kk + 1][0], sc[2 * kk + 1][1]),
                           pack_bf16(sc[2 * kk + 1][2], sc[2 * kk + 1][3])};
#pragma unroll
    for (int n2 = 0; n2 < kMaxHeadDim / 16; ++n2) {
      if (!kExactDim && n2 * 16 >= D) break;
      unsigned b[4];
      ldmatrix_x4_trans(b, sV + (kk * 16 + (lane & 7) + ((lane >> 3) & 1) * 8) * kStride + n2 * 16 + (lane >> 4) * 8);
      mma_bf16(o[2 * n2], a, b[0], b[1]);
      mma_bf16(o[2 * n2 + 1], a, b[2], b[3]);
    }
  }
}

// Normalises and stores rows g and g + 8 of this warp (columns 2 tq, 2 tq + 1 of each tile).
template <bool kExactDim>
__device__ __forceinline__ void store_rows(const float (&o)[kDimTiles][4], const float (&l)[2],
                                           const FlashParams<bf16>& p, const int (&rows)[2], std::int64_t s, int h,
                                           int D, int tq) {
#pragma unroll
  for (int i = 0; i < 2; ++i) {
    float sum = l[i];
    sum += __shfl_xor_sync(0xffffffffu, sum, 1);
    sum += __shfl_xor_sync(0xffffffffu, sum, 2);
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
        if (col < D) og[col] = detail::from_f32<bf16>(v0);
        if (col + 1 < D) og[col + 1] = detail::from_f32<bf16>(v1);
      }
    }
  }
}

template <bool kExactDim>
__global__ void __launch_bounds__(kThreads) flash_bf16_kernel(const FlashParams<bf16> p) {
  extern __shared__ __align__(16) unsigned char smem[];
  bf16* sQ = reinterpret_cast<bf16*>(smem);
  bf16* sK = sQ + kRows * kStride;
  bf16* sV = sK + kKeys * kStride;

  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  const int g = lane / 4, tq = lane % 4;  // mma fragment row group and column pair
  const int q0 = blockIdx.x * kRows, h = blockIdx.y;
  const std::int64_t s = blockIdx.z;
  const int D = kExactDim ? kMaxHeadDim : p.head_dim;
  const bf16* kg = p.k + s * p.k_seq + std::int64_t{h} * D;
  const bf16* vg = p.v + s * p.v_seq + std::int64_t{h} * D;

  load_tile<kExactDim>(sQ, p.q + s * p.q_seq + std::int64_t{h} * D, p.q_row, q0, p.lq, D);
  load_tile<kExactDim>(sK, kg, p.k_row, 0, p.lk, D);
  cp_async_commit();

  float o[kDimTiles][4] = {};
  float m[2] = {-INFINITY, -INFINITY}, l[2] = {0.f, 0.f};
  const int rows[2] = {q0 + warp * 16 + g, q0 + warp * 16 + g + 8};
  const int tiles = key_tiles(q0, kRows, p.lq, p.lk, p.causal, kKeys);
  // A warp whose rows all lie past lq (short sequences: the MST's 10 frames) only loads.
  const bool warp_active = q0 + warp * 16 < p.lq;

  for (int t = 0; t < tiles; ++t) {
    const int k0 = t * kKeys;
    cp_async_wait_all();
    __syncthreads();  // K(t) (and Q) landed; every warp is done with V(t-1)
    load_tile<kExactDim>(sV, vg, p.v_row, k0, p.lk, D);
    cp_async_commit();

    float sc[kKeyTiles][4] = {};
    if (warp_active) {
      warp_scores<kExactDim>(sc, sQ, sK, warp, lane, D);
      const bool masked = p.mask || k0 + kKeys > p.lk || (p.causal && k0 + kKeys - 1 > q0 + warp * 16);
      if (masked)
        online_softmax<true>(sc, m, l, o, p, rows, k0, tq);
      else
        online_softmax<false>(sc, m, l, o, p, rows, k0, tq);
    }

    cp_async_wait_all();
    __syncthreads();  // V(t) landed; every warp is done with K(t)
    if (t + 1 < tiles) load_tile<kExactDim>(sK, kg, p.k_row, k0 + kKeys, p.lk, D);
    cp_async_commit();

    if (warp_active) warp_pv<kExactDim>(o, sc, sV, lane, D);
  }
  cp_async_wait_all();
  store_rows<kExactDim>(o, l, p, rows, s, h, D, tq);
}
}  // namespace fa


inline bool aligned_rows(const void* p, std::int64_t seq, std::int64_t row, std::int64_t elems) {
  return reinterpret_cast<std::uintptr_t>(p) % 16 == 0 && seq % elems == 0 && row % elems == 0;
}

// The kernel before issue #5, launched as attention() launched it then.
inline void attention(Context& ctx, const bf16* q, const bf16* k, const bf16* v, bf16* o, const AttentionShape& a) {
  const float scale = a.scale != 0 ? a.scale : 1.0f / std::sqrt(static_cast<float>(a.head_dim));
  FlashParams<bf16> p{q,       k,       v,       o,       a.q_seq, a.q_row, a.k_seq, a.k_row, a.v_seq,
                      a.v_row, a.o_seq, a.o_row, static_cast<int>(a.lq), static_cast<int>(a.lk),
                      static_cast<int>(a.head_dim), scale * 1.4426950408889634f, a.mask == Mask::Causal,
                      a.additive_mask};
  const dim3 grid(static_cast<unsigned>((a.lq + fa::kRows - 1) / fa::kRows), static_cast<unsigned>(a.heads),
                  static_cast<unsigned>(a.seqs));
  const bool exact = a.head_dim == 128 && aligned_rows(q, a.q_seq, a.q_row, 8) &&
                     aligned_rows(k, a.k_seq, a.k_row, 8) && aligned_rows(v, a.v_seq, a.v_row, 8) &&
                     aligned_rows(o, a.o_seq, a.o_row, 8);
  if (exact) {
    EPONA_CUDA_CHECK(cudaFuncSetAttribute(fa::flash_bf16_kernel<true>, cudaFuncAttributeMaxDynamicSharedMemorySize, fa::kSmemBytes));
    fa::flash_bf16_kernel<true><<<grid, fa::kThreads, fa::kSmemBytes, ctx.stream()>>>(p);
  } else {
    EPONA_CUDA_CHECK(cudaFuncSetAttribute(fa::flash_bf16_kernel<false>, cudaFuncAttributeMaxDynamicSharedMemorySize, fa::kSmemBytes));
    fa::flash_bf16_kernel<false><<<grid, fa::kThreads, fa::kSmemBytes, ctx.stream()>>>(p);
  }
  EPONA_CUDA_CHECK_LAUNCH();
}

}  // namespace epona::cuda::attention_baseline
