// epona/cuda/attention/short_attention_qk_layer_norm.cuh — attention over short sequences (<= 16 tokens: the MST's
// time layers over its 10 frames) with the QK LayerNorm done inside, on the operands the
// attention loads anyway: o = attention(LN_q(q), LN_k(k), v). The separate norm pass read and
// wrote all of q and k (84 MB per MST time layer); here q and k are read once, by the attention.
//
// The norm spans every channel of a token (all heads) and the short kernel gives each
// (sequence, head) to a warp, four heads to a CTA. The CTAs of one sequence form a cluster: each
// takes the mean and squared deviations of its heads' share of every q and k row (two passes
// over shared memory), the shares meet once in distributed shared memory and are combined in
// rank order (so every CTA gets the same statistics), and each warp normalises its head's slice
// in shared memory, rounded to bf16 as layer_norm writes it, before the short kernel's scores.
// Statistics are float32 and free of cancellation, as layer_norm's two passes; only their
// summation order differs (an element can differ from the separate pass by one bf16 rounding).
#pragma once

#include <cstdint>

#include "epona/core/env.hpp"
#include "epona/cuda/attention/attention.cuh"
#include "epona/cuda/runtime/cluster.cuh"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace detail {

// The LayerNorms of q and of k (affine, float32 parameters over all heads x head_dim channels).
struct QkLayerNorm {
  const float *q_weight, *q_bias, *k_weight, *k_bias;
  float q_eps, k_eps;
};

namespace fa {
constexpr int kNormRows = 2 * kShortLen;  // a sequence's q and k rows: one lane each
constexpr int kMaxCluster = 8;            // CTAs per sequence: the portable cluster size

// Shared memory after the warps' tiles: per-warp row sums; each row's mean and squared
// deviations over this CTA's channels (other CTAs read them); the row's mean and 1/std.
struct RowStats {
  float warp[kShortWarps][kNormRows];
  float local_mean[kNormRows], local_m2[kNormRows];
  float mean[kNormRows], rstd[kNormRows];
};
inline int qk_norm_smem_bytes(int lq, int lk) { return short_smem_bytes(lq, lk) + int{sizeof(RowStats)}; }

// Lane `row` of each warp adds f(x, row) over its head's channels of row `row` (rows: q's, then
// k's, as the short kernel lays them out from sQ); returns, to threads < rows, the CTA's sum
// for row threadIdx.x.
template <class F>
__device__ __forceinline__ float cta_row_sum(RowStats& st, const bf16* sQ, int rows, F f) {
  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  float s = 0;
  if (lane < rows) {
#pragma unroll
    for (int c = 0; c < kMaxHeadDim; c += kPack) {
      float v[kPack];
      load8(sQ + lane * kStride + c, v);
#pragma unroll
      for (int i = 0; i < kPack; ++i) s += f(v[i], lane);
    }
  }
  st.warp[warp][lane] = s;
  __syncthreads();
  float t = 0;
  if (threadIdx.x < rows)
#pragma unroll
    for (int w = 0; w < kShortWarps; ++w) t += st.warp[w][threadIdx.x];
  __syncthreads();  // st.warp is free again
  return t;
}

// Mean and 1/std of every q and k row over all `groups` CTAs' channels: each CTA takes the
// mean and the squared deviations of its own channels (two passes over shared memory), the
// cluster exchanges them once and every CTA combines them in rank order (Chan et al.: the
// squared deviations plus each part's count times its mean's squared distance from the mean).
__device__ __forceinline__ void row_statistics(RowStats& st, const bf16* sQ, int rows, int groups, int lq,
                                               const QkLayerNorm& n) {
  const int t = threadIdx.x;
  constexpr float kPart = static_cast<float>(kShortWarps * kMaxHeadDim);  // channels per CTA
  const float sum = cta_row_sum(st, sQ, rows, [](float x, int) { return x; });
  if (t < rows) st.local_mean[t] = sum / kPart;
  __syncthreads();
  const float m2 = cta_row_sum(st, sQ, rows, [&](float x, int r) { return (x - st.local_mean[r]) * (x - st.local_mean[r]); });
  if (t < rows) st.local_m2[t] = m2;
  cluster_sync();  // every CTA's means and deviations written
  if (t < rows) {
    float means[kMaxCluster], m2s[kMaxCluster], total = 0;
#pragma unroll
    for (int r = 0; r < kMaxCluster; ++r)  // all remote loads issued together
      if (r < groups) means[r] = cluster_peer(st.local_mean, r)[t], m2s[r] = cluster_peer(st.local_m2, r)[t];
#pragma unroll
    for (int r = 0; r < kMaxCluster; ++r)
      if (r < groups) total += means[r];
    const float mean = total / static_cast<float>(groups);
    float m2_total = 0;
#pragma unroll
    for (int r = 0; r < kMaxCluster; ++r)
      if (r < groups) m2_total += m2s[r] + kPart * (means[r] - mean) * (means[r] - mean);
    st.mean[t] = mean;
    st.rstd[t] = 1.0f / sqrtf(m2_total / (kPart * static_cast<float>(groups)) + (t < lq ? n.q_eps : n.k_eps));
  }
  cluster_arrive();  // this CTA has read the others' statistics
  __syncthreads();
}

// Block b: sequence b / groups, heads [kShortWarps g, kShortWarps g + kShortWarps) with
// g = b % groups, its rank in the sequence's cluster of `groups` CTAs. Head dim 128, aligned
// rows (cp.async loads).
// Six blocks per multiprocessor (at most 80 registers; 34 KB of shared memory at 10 x 10): the
// 2060 blocks of an MST time layer then take 2.6 waves instead of 3.1.
// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void __launch_bounds__(kShortThreads, 6) flash_short_qk_norm_kernel(const FlashParams<bf16> p,
                                                                             const QkLayerNorm n, int groups) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  extern __shared__ __align__(16) unsigned char smem[];
  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  const std::int64_t s = blockIdx.x / groups;
  const int h = static_cast<int>(blockIdx.x % groups) * kShortWarps + warp, D = kMaxHeadDim;
  const int rows = p.lq + p.lk;
  const ShortTiles tiles = load_short_tiles<true>(smem, p, s, h, warp, lane, D);
  bf16* sQ = tiles.q;  // q's rows, then k's
  auto& st = *reinterpret_cast<RowStats*>(smem + short_smem_bytes(p.lq, p.lk));
  // A lane normalises one pack of channels (8) of every other row: its parameters, read while
  // the tiles load.
  constexpr int kPacks = kMaxHeadDim / kPack;  // 16: two rows per warp access
  const int c = (lane % kPacks) * kPack, ch = h * D + c;
  float qw[kPack], qb[kPack], kw[kPack], kb[kPack];
  load8(n.q_weight + ch, qw), load8(n.q_bias + ch, qb), load8(n.k_weight + ch, kw), load8(n.k_bias + ch, kb);
  cp_async_wait_all();
  __syncwarp();

  row_statistics(st, sQ, rows, groups, p.lq, n);
  // This warp's head slice of each q and k row, normalised in place: one rounding, as layer_norm.
  for (int r = lane / kPacks; r < rows; r += 32 / kPacks) {
    const bool is_q = r < p.lq;
    const float mean = st.mean[r], rstd = st.rstd[r];
    float v[kPack];
    load8(sQ + r * kStride + c, v);
#pragma unroll
    for (int i = 0; i < kPack; ++i) v[i] = (v[i] - mean) * rstd * (is_q ? qw[i] : kw[i]) + (is_q ? qb[i] : kb[i]);
    store8(sQ + r * kStride + c, v);
  }
  __syncwarp();

  short_attend<true>(p, tiles, s, h, lane, D);
  cluster_wait();  // no CTA frees its statistics while another may still read them
}
}  // namespace fa

// Where the kernel pays: as many queries as keys (the time layers). Measured on the H200, graph
// of calls, separate pass + short kernel -> norm inside: 515 x 16 heads x 10 x 10 (causal)
// 57.2 -> 47.4 us; the pruned last block, 1 query x 10 keys, 31.6 -> 33.3 us (its k rows cost
// the statistics' exchange while only one row in eleven is a query).
// attention_qk_norm_forced: tests run it wherever it can run, paying or not.
inline bool& attention_qk_norm_forced() {
  static bool forced = false;
  return forced;
}

}  // namespace detail

// o = attention(LN_q(q), LN_k(k), v) with the shape's strides; each LayerNorm is over all
// heads x head_dim channels of a token (contiguous in q and in k), affine, float32 parameters.
// q and k are only read. Runs (returning true) for bf16 sequences of <= 16 queries and keys,
// head dim 128 with 16-byte aligned rows, no additive mask, heads a multiple of 4 and at most
// 32, on a GPU and build with thread-block clusters, with ctx.policy().attention_qk_norm on
// (EPONA_CUDA_QK_NORM_ATTN=0: off), where it pays (as many queries as keys);
// otherwise returns false with nothing done, and the caller normalises and attends separately.
template <class T>
bool attention_qk_layer_norm(Context& ctx, const T* q, const T* k, const T* v, T* o, const AttentionShape& a,
                             const float* q_weight, const float* q_bias, float q_eps, const float* k_weight,
                             const float* k_bias, float k_eps) {
  static_assert(is_device_float<T>, "attention_qk_layer_norm takes float or bf16");
  if constexpr (!std::is_same_v<T, bf16>) {
    return false;  // float32 keeps the SIMT attention and its separate norm
  } else {
    namespace fa = detail::fa;
    if (!ctx.policy().attention_qk_norm || !detail::clusters_available(ctx)) return false;
    EPONA_CHECK(a.seqs >= 0 && a.heads >= 0 && a.lq >= 0 && a.lk >= 0, "attention_qk_layer_norm: negative extent");
    EPONA_CHECK(q && k && v && o && q_weight && q_bias && k_weight && k_bias, "attention_qk_layer_norm: null tensor");
    const auto p = detail::flash_params(q, k, v, o, a);
    const bool pays = a.lq == a.lk || detail::attention_qk_norm_forced();
    const bool fits = pays && a.lq <= fa::kShortLen && a.lk <= fa::kShortLen && !a.additive_mask &&
                      detail::exact_head_dim(p) && a.heads % fa::kShortWarps == 0 &&
                      a.heads <= fa::kShortWarps * fa::kMaxCluster && detail::aligned16(q_weight) &&
                      detail::aligned16(q_bias) && detail::aligned16(k_weight) && detail::aligned16(k_bias);
    if (!fits) return false;
    if (a.seqs == 0 || a.heads == 0 || a.lq == 0) return true;
    EPONA_CHECK(a.seqs * a.heads / fa::kShortWarps <= 0x7fffffff, "attention_qk_layer_norm: ", a.seqs,
                " sequences exceed one launch");
    const int groups = static_cast<int>(a.heads / fa::kShortWarps);
    const detail::QkLayerNorm n{q_weight, q_bias, k_weight, k_bias, q_eps, k_eps};
    const int smem = fa::qk_norm_smem_bytes(static_cast<int>(a.lq), static_cast<int>(a.lk));
    detail::allow_dynamic_smem<fa::flash_short_qk_norm_kernel<>>(fa::qk_norm_smem_bytes(fa::kShortLen, fa::kShortLen));
    detail::launch_in_clusters(fa::flash_short_qk_norm_kernel<>, dim3(static_cast<unsigned>(a.seqs * groups)),
                               static_cast<unsigned>(groups), fa::kShortThreads, smem, ctx, p, n, groups);
    return true;
  }
}

}  // namespace epona::cuda
