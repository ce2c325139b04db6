// epona/cuda/conv/dcae_temporal.cuh — the DC-AE's temporal front (Epona `dcae.py`: 5 x [causal time
// block, space block], LLaMA blocks of dim 32, 8 heads of 4, SwiGLU 256) fused: one kernel per
// block does the attention over its sequence, wo + residual, RMSNorm + SwiGLU FFN + residual and
// the NEXT block's RMSNorm + q/k/v projections + RoPE; the first block's q/k/v take one more
// launch. Same roundings as the unfused path (nn/blocks/llama_block.hpp on the CUDA kernels).
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <type_traits>
#include <vector>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/runtime/scratch.hpp"

namespace epona::cuda {

namespace temporal_detail {

constexpr int kDim = 32, kHeads = 8, kHeadDim = 4, kHidden = 256, kQkv = 3 * kDim;
constexpr int kRows = 4;                      // query rows per block of threads
constexpr int kThreads = 256;                 // phase 1: kRows x kHeads x kSlices
constexpr int kSlices = kThreads / (kRows * kHeads);  // key slices per (row, head), merged at the end
constexpr int kParts = kThreads / kDim;       // w2's reduction split in 8 parts of 32
constexpr float kLog2e = 1.4426950408889634f;
static_assert(kThreads == kHidden && kParts * kDim == kHidden && kSlices * kRows * kHeads == kThreads &&
              kHeads * kHeadDim == kDim && kRows <= kThreads / 32);

// One block's weights (row-major [out, in], as bound), norms, RoPE tables (rows x 2) and the
// sequence layout of nn::TokenSequences (row r: position t = ((r mod seqs·length) / pos_step) mod
// length, its sequence's rows base + u·pos_step).
template <class T>
struct Step {
  const T *wq, *wk, *wv, *wo, *w1, *w2, *w3;
  const float *attention_norm, *ffn_norm, *cos, *sin;
  std::int64_t seqs, length, pos_step;
  float eps;
  bool causal;
};

// 32 consecutive elements (a weight row) as float32, 16-byte loads.
template <class T>
__device__ __forceinline__ void load32(const T* p, float (&v)[kDim]) {
#pragma unroll
  for (int j0 = 0; j0 < kDim; j0 += detail::kPack) {
    float part[detail::kPack];
    detail::load8(p + j0, part);
#pragma unroll
    for (int j = 0; j < detail::kPack; ++j) v[j0 + j] = part[j];
  }
}

// Σ_j a(j) · w[j] over 32 values, w a weight row in memory (16-byte loads).
template <class T, class Value>
__device__ __forceinline__ float row_dot(Value a, const T* w) {
  float s = 0.f;
#pragma unroll
  for (int j0 = 0; j0 < kDim; j0 += detail::kPack) {
    float wv[detail::kPack];
    detail::load8(w + j0, wv);
#pragma unroll
    for (int j = 0; j < detail::kPack; ++j) s = fmaf(a(j0 + j), wv[j], s);
  }
  return s;
}
// a_j from lane j of the warp.
template <class T>
__device__ __forceinline__ float row_dot_lanes(float a, const T* w) {
  return row_dot([a](int j) { return __shfl_sync(0xffffffffu, a, j); }, w);
}
// a in shared memory (the same for the whole warp: broadcast).
template <class T>
__device__ __forceinline__ float row_dot_shared(const float* a, const T* w) {
  return row_dot([a](int j) { return a[j]; }, w);
}

// RMSNorm (weight only) of the row whose channel c = lane this warp holds, rounded to T.
template <class T>
__device__ __forceinline__ float rms_normed(float xc, const float* weight, float eps, int lane) {
  const float rr = 1.0f / sqrtf(detail::warp_sum(xc * xc) / static_cast<float>(kDim) + eps);
  return detail::round_to<T>((xc * rr) * weight[lane]);
}

// One warp, lane c: qkv[r] = [rope(q), rope(k), v] of RMSNorm(x_r) for step s, each rounded to T
// after its projection and again after the rotation (as the unfused linear + apply_rope).
template <class T>
__device__ __forceinline__ void project_qkv(float xc, std::int64_t r, const Step<T>& s, T* __restrict__ qkv,
                                            int lane) {
  const float h = rms_normed<T>(xc, s.attention_norm, s.eps, lane);
  float q = detail::round_to<T>(row_dot_lanes(h, s.wq + lane * kDim));
  float k = detail::round_to<T>(row_dot_lanes(h, s.wk + lane * kDim));
  const float v = row_dot_lanes(h, s.wv + lane * kDim);
  const int pair = (lane & (kHeadDim - 1)) >> 1;
  const float cs = s.cos[r * (kHeadDim / 2) + pair], sn = s.sin[r * (kHeadDim / 2) + pair];
  const float q_other = __shfl_xor_sync(0xffffffffu, q, 1), k_other = __shfl_xor_sync(0xffffffffu, k, 1);
  if ((lane & 1) == 0) {  // (a, b) -> (a·cos - b·sin, a·sin + b·cos)
    q = cs * q - sn * q_other;
    k = cs * k - sn * k_other;
  } else {
    q = sn * q_other + cs * q;
    k = sn * k_other + cs * k;
  }
  T* out = qkv + r * kQkv;
  out[lane] = detail::from_f32<T>(q);
  out[kDim + lane] = detail::from_f32<T>(k);
  out[2 * kDim + lane] = detail::from_f32<T>(v);
}

// The first step's q/k/v: one warp per row.
template <class T>
__global__ void __launch_bounds__(kThreads) qkv_kernel(const float* __restrict__ x, T* __restrict__ qkv,
                                                       std::int64_t rows, Step<T> s) {
  const int lane = threadIdx.x & 31;
  const std::int64_t r = blockIdx.x * std::int64_t{kThreads / 32} + (threadIdx.x >> 5);
  if (r >= rows) return;  // whole warps leave together
  project_qkv(x[r * kDim + lane], r, s, qkv, lane);
}

// One block of kRows query rows through step s (and the next step's q/k/v when `has_next`).
//  1. attention: thread (row, head, slice) runs an online softmax over keys slice, slice + 8, …
//     of the row's sequence (causal: up to its own position); slices merge by shuffles.
//  2. warp = row, lane = c: x1 = x + round(o·woᵀ); h2 = RMSNorm_ffn(x1).
//  3. thread = hidden unit: g = round(value · round(SiLU(gate))), gate/value rounded first.
//  4. warp = part of 32 hidden units, lane = c: partial sums of g·w2ᵀ; summed in part order in 5.
//  5. warp = row: x2 = x1 + round(Σ parts); stored; next step's q/k/v from x2.
template <class T>
__global__ void __launch_bounds__(kThreads) block_kernel(float* __restrict__ x, const T* __restrict__ qkv,
                                                         T* __restrict__ qkv_next, std::int64_t rows, Step<T> s,
                                                         Step<T> next, bool has_next) {
  __shared__ float s_o[kRows][kDim], s_h[kRows][kDim], s_g[kRows][kHidden], s_part[kParts][kRows][kDim];
  const int t = threadIdx.x, lane = t & 31, warp = t >> 5;
  const std::int64_t row0 = blockIdx.x * std::int64_t{kRows};

  {  // 1. attention
    const int slice = t % kSlices, head = (t / kSlices) % kHeads, rl = t / (kSlices * kHeads);
    const std::int64_t r = row0 + rl;
    float m = -INFINITY, l = 0.f, acc[kHeadDim] = {0.f, 0.f, 0.f, 0.f};
    if (r < rows) {
      const std::int64_t block = s.seqs * s.length;
      const std::int64_t pos = ((r % block) / s.pos_step) % s.length, base = r - pos * s.pos_step;
      const std::int64_t keys = s.causal ? pos + 1 : s.length;
      float q[kHeadDim];
      detail::load4(qkv + r * kQkv + head * kHeadDim, q);
      const float scale = 1.0f / sqrtf(static_cast<float>(kHeadDim)) * kLog2e;  // softmax in base 2
#pragma unroll
      for (int e = 0; e < kHeadDim; ++e) q[e] *= scale;
      for (std::int64_t u = slice; u < keys; u += kSlices) {
        const T* kv = qkv + (base + u * s.pos_step) * kQkv + head * kHeadDim;
        float k[kHeadDim], v[kHeadDim];
        detail::load4(kv + kDim, k);
        detail::load4(kv + 2 * kDim, v);
        const float sc = q[0] * k[0] + q[1] * k[1] + q[2] * k[2] + q[3] * k[3];
        const float m_new = fmaxf(m, sc);
        const float alpha = exp2f(m - m_new), p = exp2f(sc - m_new);
        l = l * alpha + p;
        const float pv = detail::round_to<T>(p);  // P is rounded to T for the P·V product (flash bf16)
#pragma unroll
        for (int e = 0; e < kHeadDim; ++e) acc[e] = acc[e] * alpha + pv * v[e];
        m = m_new;
      }
    }
#pragma unroll
    for (int o = 1; o < kSlices; o <<= 1) {  // merge the slices (lanes differing in the low bits)
      const float m_o = __shfl_xor_sync(0xffffffffu, m, o), l_o = __shfl_xor_sync(0xffffffffu, l, o);
      const float m_new = fmaxf(m, m_o);
      const float a = m == -INFINITY ? 0.f : exp2f(m - m_new), b = m_o == -INFINITY ? 0.f : exp2f(m_o - m_new);
      l = l * a + l_o * b;
#pragma unroll
      for (int e = 0; e < kHeadDim; ++e) acc[e] = acc[e] * a + __shfl_xor_sync(0xffffffffu, acc[e], o) * b;
      m = m_new;
    }
    if (slice == 0) {
      const float inv = l > 0.f ? 1.0f / l : 0.f;
#pragma unroll
      for (int e = 0; e < kHeadDim; ++e) s_o[rl][head * kHeadDim + e] = detail::round_to<T>(acc[e] * inv);
    }
  }
  __syncthreads();

  const std::int64_t my_row = row0 + warp;  // phases 2 and 5
  float x1 = 0.f;
  if (warp < kRows) {  // 2. wo, residual, ffn norm
    const float proj = detail::round_to<T>(row_dot_shared(s_o[warp], s.wo + lane * kDim));
    x1 = (my_row < rows ? x[my_row * kDim + lane] : 0.f) + proj;
    s_h[warp][lane] = rms_normed<T>(x1, s.ffn_norm, s.eps, lane);
  }
  __syncthreads();

  {  // 3. SwiGLU hidden unit t for every row
    float w1[kDim], w3[kDim];
    load32(s.w1 + t * kDim, w1);
    load32(s.w3 + t * kDim, w3);
#pragma unroll
    for (int rl = 0; rl < kRows; ++rl) {
      float gate = 0.f, value = 0.f;
#pragma unroll
      for (int j = 0; j < kDim; ++j) {
        gate = fmaf(s_h[rl][j], w1[j], gate);
        value = fmaf(s_h[rl][j], w3[j], value);
      }
      gate = detail::round_to<T>(gate);
      const float act = detail::round_to<T>(gate / (1.0f + expf(-gate)));
      s_g[rl][t] = detail::round_to<T>(detail::round_to<T>(value) * act);
    }
  }
  __syncthreads();

  {  // 4. partial products with w2 over this warp's 32 hidden units
    float w2[kDim];
    load32(s.w2 + lane * kHidden + warp * kDim, w2);
#pragma unroll
    for (int rl = 0; rl < kRows; ++rl) {
      float sum = 0.f;
#pragma unroll
      for (int j = 0; j < kDim; ++j) sum = fmaf(s_g[rl][warp * kDim + j], w2[j], sum);
      s_part[warp][rl][lane] = sum;
    }
  }
  __syncthreads();

  if (warp < kRows && my_row < rows) {  // 5. residual, store, next step's q/k/v
    float sum = 0.f;
#pragma unroll
    for (int p = 0; p < kParts; ++p) sum += s_part[p][warp][lane];
    const float x2 = x1 + detail::round_to<T>(sum);
    x[my_row * kDim + lane] = x2;
    if (has_next) project_qkv(x2, my_row, next, qkv_next, lane);
  }
}

}  // namespace temporal_detail

// Runs a chain of LLaMA TransformerBlocks (nn/blocks/llama_block.hpp) over the float32 token rows x
// (rows, 32) in place: `steps` in order, each {block, seq (nn::TokenSequences), cos, sin (its
// RoPE tables in device memory)}. Weights of T; dim 32, 8 heads, hidden 256 only. False (nothing
// done) when fusion is off or a block has other extents or misaligned weights: the caller then
// runs the blocks one by one.
template <class Steps>
bool fused_transformer_blocks(Context& ctx, float* x, std::int64_t rows, const Steps& steps) {
  using namespace temporal_detail;
  if (!ctx.policy().dcae_fusion || steps.empty() || rows <= 0) return false;
  using Block = std::remove_cv_t<std::remove_pointer_t<decltype(steps.front().block)>>;
  using T = std::remove_cv_t<std::remove_reference_t<decltype(*steps.front().block->wq.data())>>;
  static_assert(is_device_float<T>, "fused_transformer_blocks takes float or bf16 weights");
  std::vector<Step<T>> plan;
  for (const auto& st : steps) {
    const Block& b = *st.block;
    if (b.dim != kDim || b.heads != kHeads || b.ffn_hidden != kHidden || st.seq.rows() != rows) return false;
    for (const void* p : {static_cast<const void*>(b.wq.data()), static_cast<const void*>(b.wk.data()),
                          static_cast<const void*>(b.wv.data()), static_cast<const void*>(b.wo.data()),
                          static_cast<const void*>(b.w1.data()), static_cast<const void*>(b.w2.data()),
                          static_cast<const void*>(b.w3.data())})
      if (!p || !detail::aligned16(p)) return false;
    plan.push_back(Step<T>{b.wq.data(), b.wk.data(), b.wv.data(), b.wo.data(), b.w1.data(), b.w2.data(), b.w3.data(),
                           b.attention_norm.data(), b.ffn_norm.data(), st.cos, st.sin, st.seq.seqs, st.seq.length,
                           st.seq.pos_step, b.norm_eps, st.seq.causal});
  }
  EPONA_CHECK(x && detail::aligned16(x), "fused_transformer_blocks: token rows must be 16-byte aligned");
  Tensor<T, Cuda> qkv[2] = {scratch_tensor<T>(ctx, {rows, kQkv}), scratch_tensor<T>(ctx, {rows, kQkv})};
  const auto blocks = [](std::int64_t n, std::int64_t per) { return static_cast<unsigned>((n + per - 1) / per); };
  EPONA_CHECK(rows / kRows < 0x7fffffff, "fused_transformer_blocks: ", rows, " rows exceed one launch");
  qkv_kernel<<<blocks(rows, kThreads / 32), kThreads, 0, ctx.stream()>>>(x, qkv[0].data(), rows, plan[0]);
  EPONA_CUDA_CHECK_LAUNCH();
  for (std::size_t i = 0; i < plan.size(); ++i) {
    const bool has_next = i + 1 < plan.size();
    block_kernel<<<blocks(rows, kRows), kThreads, 0, ctx.stream()>>>(x, qkv[i % 2].data(), qkv[(i + 1) % 2].data(),
                                                                     rows, plan[i], plan[has_next ? i + 1 : i], has_next);
    EPONA_CUDA_CHECK_LAUNCH();
  }
  return true;
}

}  // namespace epona::cuda
