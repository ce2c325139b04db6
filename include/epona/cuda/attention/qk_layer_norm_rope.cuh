// epona/cuda/attention/qk_layer_norm_rope.cuh — the MST attention's QK-norm (nn.LayerNorm over all
// channels of q and of k, in place) and, in the space layers, the 2-D RoPE of q and k, in one
// launch and one read and one write of each row instead of four launches and three passes. The
// same row kernel (norm.cuh) and rotation as layer_norm + apply_rope, but the rotation runs on
// the norm's float32 results: bf16 rows are rounded once (the unfused ops round twice), float32
// rows agree with the unfused ops within a few ulp.
#pragma once

#include <cstdint>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/pointwise/norm.cuh"

namespace epona::cuda {

namespace detail {

template <class T>
struct QkNormRopeArgs {
  T *q, *k;                    // (rows_q, n) and (rows_k, n), normalised and rotated in place
  std::int64_t rows_q, rows_k, n;
  const float *q_weight, *q_bias, *k_weight, *k_bias;
  float q_eps, k_eps;
  int head_dim;                // heads side by side along n
  const float *cos, *sin;      // (rows, head_dim / 2) for row r of q and of k; null: no rotation
  bool reverse;                // warps take the rows last to first
};

// The four angles of the 8 channels starting at channel c0 of a row (a pack inside one head):
// consecutive in the table row (cos, sin), one 16-byte load each.
struct PackAngles {
  float4 cos, sin;
  __device__ __forceinline__ PackAngles(int c0, int head_dim, const float* cos_row, const float* sin_row) {
    const int j0 = (c0 % head_dim) / 2;
    cos = *reinterpret_cast<const float4*>(cos_row + j0);
    sin = *reinterpret_cast<const float4*>(sin_row + j0);
  }
};

// Interleaved pairs (2j, 2j+1) of a pack rotated by its angles: float32 arithmetic as rope_kernel.
__device__ __forceinline__ void rotate_pack(float (&v)[kPack], const PackAngles& t) {
  const float cs[4] = {t.cos.x, t.cos.y, t.cos.z, t.cos.w}, sn[4] = {t.sin.x, t.sin.y, t.sin.z, t.sin.w};
#pragma unroll
  for (int i = 0; i < kPack / 2; ++i) {
    const float a = v[2 * i], b = v[2 * i + 1];
    v[2 * i] = cs[i] * a - sn[i] * b;
    v[2 * i + 1] = sn[i] * a + cs[i] * b;
  }
}

// One warp per row of q, then of k (warps past rows_q take k's rows). The norm is norm_row as
// the warp-per-row LayerNorm runs it; each pack is rotated in registers before its one store,
// so q and k are rounded once, after the rotation, as the official recipe (float32 norm and
// rotation, bf16 for the attention) rounds them.
template <class T, int P>
__global__ void __launch_bounds__(32 * kNormWarps) qk_layer_norm_rope_kernel(QkNormRopeArgs<T> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t item = blockIdx.x * std::int64_t{kNormWarps} + threadIdx.x / 32;
  if (item >= a.rows_q + a.rows_k) return;
  const std::int64_t w = pass_index(item, a.rows_q + a.rows_k, a.reverse);
  const bool is_q = w < a.rows_q;
  const std::int64_t row = is_q ? w : w - a.rows_q;
  T* x = is_q ? a.q : a.k;
  const RowNormArgs<T, T, T, T, float> norm{x,          nullptr, nullptr, nullptr,
                                            x,          is_q ? a.q_weight : a.k_weight,
                                            is_q ? a.q_bias : a.k_bias, is_q ? a.rows_q : a.rows_k,
                                            a.n,        is_q ? a.q_eps : a.k_eps};
  const int lane = threadIdx.x & 31;
  const auto warp = [](float v) { return warp_sum(v); };
  if (!a.cos) return norm_row<P, false, false>(norm, row, lane, 32, warp);
  const int pairs = a.head_dim / 2;
  const float* cos = a.cos + row * pairs;
  const float* sin = a.sin + row * pairs;
  if ((32 * kPack) % a.head_dim == 0) {
    // A lane's packs (lane + 32 i) all start at the same channel of their heads: their angles are
    // loaded once, with the row, instead of after the statistics for every pack.
    const PackAngles angles(lane * kPack, a.head_dim, cos, sin);
    return norm_row<P, false, false>(norm, row, lane, 32, warp,
                                     [&](float (&v)[kPack], int) { rotate_pack(v, angles); });
  }
  norm_row<P, false, false>(norm, row, lane, 32, warp, [&](float (&v)[kPack], int c0) {
    rotate_pack(v, PackAngles(c0, a.head_dim, cos, sin));
  });
}

}  // namespace detail

// q (rows_q, n) = LN_q(q), k (rows_k, n) = LN_k(k) in place (affine, float32 parameters), then,
// with cos/sin, both rotated as apply_rope with table row r for row r, rounded once. One launch
// when the rows fit the warp-per-row LayerNorm that layer_norm itself would pick for each of q
// and k (so the statistics are the unfused ops' to the bit); returns false, doing nothing, otherwise.
template <class T>
bool layer_norm_rope_qk(Context& ctx, T* q, std::int64_t rows_q, T* k, std::int64_t rows_k, std::int64_t n,
                        const float* q_weight, const float* q_bias, float q_eps, const float* k_weight,
                        const float* k_bias, float k_eps, std::int64_t head_dim, const float* cos, const float* sin) {
  static_assert(is_device_float<T>, "layer_norm_rope_qk takes float or bf16");
  EPONA_CHECK(rows_q >= 0 && rows_k >= 0 && n > 0 && head_dim > 0 && head_dim % 2 == 0 && n % head_dim == 0,
              "layer_norm_rope_qk: bad extent (rows ", rows_q, " and ", rows_k, ", width ", n, ", head_dim ",
              head_dim, ")");
  EPONA_CHECK((cos == nullptr) == (sin == nullptr), "layer_norm_rope_qk: cos and sin must both be given or not");
  const std::int64_t warp_min = detail::warp_rows_min(ctx);
  // Packs of 8 channels inside one head and 16-byte table rows for rotate_pack's loads.
  const bool table_ok = !cos || (head_dim % detail::kPack == 0 && detail::aligned16(cos) && detail::aligned16(sin));
  const bool fits = table_ok && n <= detail::kWarpRowMax && rows_q >= warp_min && rows_k >= warp_min &&
                    detail::packable(q, n, n) && detail::packable(k, n, n) && detail::packable(q_weight, n, 0) &&
                    detail::packable(q_bias, n, 0) && detail::packable(k_weight, n, 0) &&
                    detail::packable(k_bias, n, 0);
  if (!fits) return false;
  const detail::QkNormRopeArgs<T> a{q,      k,     rows_q, rows_k,  n,   q_weight, q_bias, k_weight, k_bias,
                                    q_eps,  k_eps, static_cast<int>(head_dim), cos, sin,
                                    ctx.policy().reversed_passes};
  const auto blocks = static_cast<unsigned>((rows_q + rows_k + detail::kNormWarps - 1) / detail::kNormWarps);
  detail::with_warp_row_packs(n, [&](auto packs_per_lane) {  // the choice layer_norm makes
    detail::launch_after(detail::qk_layer_norm_rope_kernel<T, decltype(packs_per_lane)::value>, blocks,
                         32 * detail::kNormWarps, 0, ctx, a);
  });
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

}  // namespace epona::cuda
