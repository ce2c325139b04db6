// epona/cuda/attention/qk_rms_norm_rope.cuh — the DiTs' per-head QK RMSNorm followed by rotary embedding in
// one pass (one warp per token and head, in place on packed QKV): the two kernels rms_norm_heads
// and apply_rope in sequence, with the same roundings — (x·rrms) rounded to the storage type,
// times the float32 scale, rounded (the official QKNorm), then the float32 rotation of the
// rounded pair, rounded again (`.type_as(x)`) — but one read and one write instead of two each
// (head dim 128: each lane keeps 4 channels in registers, 8- or 16-byte accesses).
// qk_norm_rope does the queries and keys of several row ranges, each with its own norm scales
// (a double block's two streams; a pruned single block's few queries), in one launch; for many
// bf16 heads of 128 a warp takes a group of a row's heads with 16-byte accesses (the row path,
// same bits).
#pragma once

#include <array>
#include <cstdint>
#include <type_traits>

#include "epona/core/env.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace detail {

// One head of head_dim channels at p, normed with `scale` and rotated by the row's cos/sin
// (head_dim/2 entries each), by the 32 lanes of a warp.
template <class T>
__device__ __forceinline__ void norm_rope_head(T* p, int lane, int head_dim, const float* scale, float eps,
                                               const float* cr, const float* sr) {
  const int pairs = head_dim / 2;
  float ss = 0;
  for (int j = lane; j < pairs; j += 32) {
    const float a = to_f32(p[2 * j]), b = to_f32(p[2 * j + 1]);
    ss += a * a + b * b;
  }
  const float rr = 1.0f / sqrtf(warp_sum(ss) / static_cast<float>(head_dim) + eps);
  for (int j = lane; j < pairs; j += 32) {
    const float a = round_to<T>(round_to<T>(to_f32(p[2 * j]) * rr) * scale[2 * j]);
    const float b = round_to<T>(round_to<T>(to_f32(p[2 * j + 1]) * rr) * scale[2 * j + 1]);
    const float c = cr[j], s = sr[j];
    p[2 * j] = from_f32<T>(c * a - s * b);
    p[2 * j + 1] = from_f32<T>(s * a + c * b);
  }
}

// The arithmetic of the head-dim-128 paths, one piece of code so that they give the same bits:
// the squares of 4 consecutive channels (in this order), the inverse RMS of a head's sum,
// a channel normed and scaled (rounded twice), and the rotation of one (a, b) pair.
constexpr int kVecHeadDim = 128;
__device__ __forceinline__ float sum_sq4(const float* v) {
  return v[0] * v[0] + v[1] * v[1] + (v[2] * v[2] + v[3] * v[3]);
}
__device__ __forceinline__ float inv_rms128(float sum_sq, float eps) {
  return 1.0f / sqrtf(sum_sq / static_cast<float>(kVecHeadDim) + eps);
}
template <class T>
__device__ __forceinline__ float norm_scaled(float v, float rr, float scale) {
  return round_to<T>(round_to<T>(v * rr) * scale);
}
__device__ __forceinline__ void rotate_pair(float c, float s, float a, float b, float* out) {
  out[0] = c * a - s * b;
  out[1] = s * a + c * b;
}

// The same for head_dim = 128 with each lane holding 4 consecutive channels (2 pairs) in
// registers: one 8-byte (bf16) or 16-byte (float) load and store per lane instead of two
// passes of 2-byte accesses. Same roundings; the squares are summed in another order.
template <class T>
__device__ __forceinline__ void norm_rope_head128(T* p, int lane, const float* scale, float eps, const float* cr,
                                                  const float* sr) {
  float v[4];
  load4(p + 4 * lane, v);
  const float rr = inv_rms128(warp_sum(sum_sq4(v)), eps);
#pragma unroll
  for (int i = 0; i < 4; ++i) v[i] = norm_scaled<T>(v[i], rr, scale[4 * lane + i]);
  float out[4];
#pragma unroll
  for (int q = 0; q < 2; ++q) rotate_pair(cr[2 * lane + q], sr[2 * lane + q], v[2 * q], v[2 * q + 1], out + 2 * q);
  store4(p + 4 * lane, out);
}

// A head by the warp: the register path when Vec (head_dim 128, 4-element aligned heads).
template <bool Vec, class T>
__device__ __forceinline__ void norm_rope_any(T* p, int lane, int head_dim, const float* scale, float eps,
                                              const float* cr, const float* sr) {
  if constexpr (Vec)
    norm_rope_head128(p, lane, scale, eps, cr, sr);
  else
    norm_rope_head(p, lane, head_dim, scale, eps, cr, sr);
}

template <bool Vec, class T>
__global__ void rms_norm_rope_kernel(T* x, std::int64_t rows, std::int64_t row_stride, int heads, int head_dim,
                                     const float* scale, float eps, const float* cos, const float* sin) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;
  if (item >= rows * heads) return;
  const std::int64_t r = item / heads;
  const int pairs = head_dim / 2;
  norm_rope_any<Vec>(x + r * row_stride + (item % heads) * head_dim, threadIdx.x & 31, head_dim, scale, eps,
                     cos + r * pairs, sin + r * pairs);
}

// Heads of head_dim at x + r·row_stride (+ offset) can take the register path.
template <class T>
bool vector_heads(const T* x, std::int64_t row_stride, std::int64_t head_dim, std::int64_t offset = 0) {
  return head_dim == kVecHeadDim && reinterpret_cast<std::uintptr_t>(x) % (4 * sizeof(T)) == 0 &&
         row_stride % 4 == 0 && offset % 4 == 0;
}

// The row ranges of one qk_norm_rope launch: range i covers `rows[i]` rows from `first[i]` of
// the q (part 2i) or k (part 2i+1) block, normed with scale[i]; items before part p: start[p].
constexpr int kQkParts = 8;  // up to 4 segments x {queries, keys}
template <class T>
struct QkRopeParts {
  T* qkv;
  std::int64_t row_stride, k_offset;
  int heads, head_dim, parts;
  float eps;
  const float* cos;
  const float* sin;
  std::int64_t first[kQkParts], start[kQkParts + 1];
  const float* scale[kQkParts];
  QkItems items{};  // the parts repeat for each item (start[parts] heads an item)

  __host__ __device__ std::int64_t heads_total() const { return items.count * start[parts]; }
  // Head index u of all items as (item 0's head index, the item's qkv and RoPE table).
  __host__ __device__ std::int64_t locate(std::int64_t u, T*& rows, const float*& cos_rows, const float*& sin_rows) const {
    const std::int64_t item = u / start[parts], pairs = head_dim / 2;
    rows = qkv + item * items.stride * row_stride;
    cos_rows = cos + item * items.rope_stride * pairs;
    sin_rows = sin + item * items.rope_stride * pairs;
    return u - item * start[parts];
  }
};

template <bool Vec, class T>
__global__ void qk_norm_rope_kernel(QkRopeParts<T> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t unit = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;
  if (unit >= a.heads_total()) return;
  T* qkv;
  const float *cos, *sin;
  const std::int64_t item = a.locate(unit, qkv, cos, sin);
  int p = 0;
  while (item >= a.start[p + 1]) ++p;
  const std::int64_t local = item - a.start[p], r = a.first[p] + local / a.heads;
  const int pairs = a.head_dim / 2;
  T* head = qkv + r * a.row_stride + (p & 1) * a.k_offset + (local % a.heads) * a.head_dim;
  norm_rope_any<Vec>(head, threadIdx.x & 31, a.head_dim, a.scale[p], a.eps, cos + r * pairs, sin + r * pairs);
}

// The row path of qk_norm_rope (head_dim 128, 16-byte aligned rows, tables and scales): a warp
// takes a group of query or key heads of one row of one part, each lane 16 bytes of a head
// (bf16: 8 channels, 16 lanes a head, two heads per access; float: 4 channels, 32 lanes), so
// a row's cos/sin and the part's scale are loaded once for the group and all the group's loads
// are in flight together (the head-per-warp kernel had one 8-byte load per lane in flight).
// Bit-identical to norm_rope_head128: the same helpers, and the same tree for the sum of
// squares — a 16-lane head's lane j holds that kernel's lanes 2j and 2j + 1, whose two 4-channel
// partials are each reduced over the 16 lanes in that kernel's order and then added (its last
// butterfly step).
template <class T>
struct RowLanes {
  static constexpr int kElems = 16 / static_cast<int>(sizeof(T));  // channels of a lane
  static constexpr int kPerHead = kVecHeadDim / kElems;              // lanes of a head
  static constexpr int kHeads = 32 / kPerHead;                       // heads per warp access
};

template <int Lanes>
__device__ __forceinline__ float lanes_sum(float v) {
#pragma unroll
  for (int o = Lanes / 2; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}
template <class T>
__device__ __forceinline__ void load_lane(const T* p, float (&v)[RowLanes<T>::kElems]) {
  if constexpr (RowLanes<T>::kElems == kPack) load8(p, v); else load4(p, v);
}
template <class T>
__device__ __forceinline__ void store_lane(T* p, const float (&v)[RowLanes<T>::kElems]) {
  if constexpr (RowLanes<T>::kElems == kPack) store8(p, v); else store4(p, v);
}

// One lane's channels of a head: norm, scale, rotate, in place (every lane of the warp calls it).
template <class T>
__device__ __forceinline__ void norm_rope_lane(float (&v)[RowLanes<T>::kElems], const float* scale, float eps,
                                               const float* cr, const float* sr) {
  constexpr int E = RowLanes<T>::kElems;
  float sum = 0;
#pragma unroll
  for (int i = 0; i < E / 4; ++i) sum += lanes_sum<RowLanes<T>::kPerHead>(sum_sq4(v + 4 * i));  // 0 + s0 (+ s1)
  const float rr = inv_rms128(sum, eps);
#pragma unroll
  for (int i = 0; i < E; ++i) v[i] = norm_scaled<T>(v[i], rr, scale[i]);
#pragma unroll
  for (int i = 0; i < E / 2; ++i) rotate_pair(cr[i], sr[i], v[2 * i], v[2 * i + 1], v + 2 * i);
}

// Accesses: warp accesses per group (bf16: 2 heads each, float: 1).
template <class T, int Accesses>
__global__ void qk_norm_rope_rows_kernel(QkRopeParts<T> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  using L = RowLanes<T>;
  constexpr int E = L::kElems, group_heads = Accesses * L::kHeads;
  const int groups = (a.heads + group_heads - 1) / group_heads;
  const std::int64_t item = blockIdx.x * std::int64_t{blockDim.x / 32} + threadIdx.x / 32;  // (part, row, group)
  if (item / groups * a.heads >= a.heads_total()) return;
  T* qkv;
  const float *cos, *sin;
  const std::int64_t head0 = a.locate(item / groups * a.heads, qkv, cos, sin);
  int p = 0;
  while (head0 >= a.start[p + 1]) ++p;
  const std::int64_t r = a.first[p] + (head0 - a.start[p]) / a.heads;
  const int lane = threadIdx.x & 31, c0 = (lane % L::kPerHead) * E;
  const int h0 = static_cast<int>(item % groups) * group_heads + lane / L::kPerHead;  // this lane's first head
  float cr[E / 2], sr[E / 2], scale[E];
  const float* cos_row = cos + r * (kVecHeadDim / 2) + c0 / 2;
  const float* sin_row = sin + r * (kVecHeadDim / 2) + c0 / 2;
#pragma unroll
  for (int i = 0; i < E / 2; ++i) cr[i] = cos_row[i], sr[i] = sin_row[i];
#pragma unroll
  for (int i = 0; i < E; ++i) scale[i] = a.scale[p][c0 + i];
  T* row = qkv + r * a.row_stride + (p & 1) * a.k_offset + c0;
  float v[Accesses][E] = {};
#pragma unroll
  for (int u = 0; u < Accesses; ++u)
    if (const int h = h0 + u * L::kHeads; h < a.heads) load_lane(row + h * kVecHeadDim, v[u]);
#pragma unroll
  for (int u = 0; u < Accesses; ++u) {
    norm_rope_lane<T>(v[u], scale, a.eps, cr, sr);
    if (const int h = h0 + u * L::kHeads; h < a.heads) store_lane(row + h * kVecHeadDim, v[u]);
  }
}

// The row path's conditions: bf16, enough heads, head dim 128 and every 16-byte access aligned.
// Measured on the H200 (graph of calls on cold buffers, per call, head-per-warp -> row path in
// groups of 4 accesses): VisDiT 1027 rows x 16 heads 9.72 -> 7.50 us, but TrajDiT 530 x 8
// 3.83 -> 4.07, its pruned block 2.75 -> 3.59, float32 VisDiT 11.65 -> 12.78 (its head-per-warp
// accesses are 16-byte already): with fewer heads than 128 per SM the finer split keeps more
// loads in flight.
// qk_rows_forced: tests and benchmarks take the row path wherever it can run, paying or not.
inline bool& qk_rows_forced() {
  static bool forced = false;
  return forced;
}
template <class T>
bool row_path(Context& ctx, const QkRopeParts<T>& a) {
  const auto elems16 = [](std::int64_t n) { return n * static_cast<std::int64_t>(sizeof(T)) % 16 == 0; };
  const bool pays = std::is_same_v<T, bf16> && a.heads_total() >= std::int64_t{128} * ctx.info().multiprocessors;
  bool ok = (pays || qk_rows_forced()) && a.head_dim == kVecHeadDim && aligned16(a.qkv) && elems16(a.row_stride) &&
            elems16(a.k_offset) && aligned16(a.cos) && aligned16(a.sin);
  for (int p = 0; p < a.parts; ++p) ok = ok && aligned16(a.scale[p]);
  return ok;
}

// Warp accesses per head group of the row path (2, 4 or 8; benchmarks compare them).
inline int& qk_rows_accesses() {
  static int accesses = 4;
  return accesses;
}

template <class T, int Accesses>
void launch_qk_rows(Context& ctx, const QkRopeParts<T>& a) {
  constexpr int threads = 128, group_heads = Accesses * RowLanes<T>::kHeads;
  const std::int64_t warps = a.heads_total() / a.heads * ((a.heads + group_heads - 1) / group_heads);
  const std::int64_t blocks = (warps + threads / 32 - 1) / (threads / 32);
  EPONA_CHECK(blocks <= 0x7fffffff, "qk_norm_rope: ", warps, " head groups exceed one launch");
  launch_after(qk_norm_rope_rows_kernel<T, Accesses>, static_cast<unsigned>(blocks), threads, 0, ctx, a);
}
template <class T>
void launch_qk_rows(Context& ctx, const QkRopeParts<T>& a) {
  switch (qk_rows_accesses()) {
    case 2: return launch_qk_rows<T, 2>(ctx, a);
    case 8: return launch_qk_rows<T, 8>(ctx, a);
    default: return launch_qk_rows<T, 4>(ctx, a);
  }
}

inline void check_norm_rope_extent(std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                                   std::int64_t head_dim, const char* what) {
  EPONA_CHECK(rows >= 0 && heads > 0 && head_dim > 0 && head_dim % 2 == 0 && head_dim <= 0x7fffffff &&
                  heads <= 0x7fffffff,
              what, ": bad extent (rows ", rows, ", heads ", heads, ", head_dim ", head_dim, ")");
  EPONA_CHECK(row_stride >= heads * head_dim, what, ": row stride ", row_stride, " is narrower than ", heads,
              " heads of ", head_dim);
}

constexpr int kNormRopeThreads = 256, kNormRopeWarps = kNormRopeThreads / 32;

inline unsigned norm_rope_blocks(std::int64_t items, const char* what) {
  const std::int64_t blocks = (items + kNormRopeWarps - 1) / kNormRopeWarps;
  EPONA_CHECK(blocks <= 0x7fffffff, what, ": ", items, " heads exceed one launch");
  return static_cast<unsigned>(blocks);
}

}  // namespace detail

// In place on `rows` tokens whose heads start at x + r·row_stride: per head RMSNorm (eps, float32
// scale of head_dim) then the rotation by cos/sin rows r of (rows, head_dim/2) tables.
template <class T>
void rms_norm_rope_heads(Context& ctx, T* x, std::int64_t rows, std::int64_t row_stride, std::int64_t heads,
                         std::int64_t head_dim, const float* scale, float eps, const float* cos, const float* sin) {
  static_assert(is_device_float<T>, "rms_norm_rope_heads takes float or bf16");
  detail::check_norm_rope_extent(rows, row_stride, heads, head_dim, "rms_norm_rope_heads");
  EPONA_CHECK(scale != nullptr && cos != nullptr && sin != nullptr, "rms_norm_rope_heads: null scale or table");
  if (rows == 0) return;
  const unsigned blocks = detail::norm_rope_blocks(rows * heads, "rms_norm_rope_heads");
  const auto kernel = detail::vector_heads(x, row_stride, head_dim) ? detail::rms_norm_rope_kernel<true, T>
                                                                    : detail::rms_norm_rope_kernel<false, T>;
  detail::launch_after(kernel, blocks, detail::kNormRopeThreads, 0, ctx, x, rows, row_stride,
                       static_cast<int>(heads), static_cast<int>(head_dim), scale, eps, cos, sin);
}

// Queries and keys of several row ranges of one packed buffer in one launch: token r's query
// heads start at qkv + r·row_stride, its key heads k_offset further. Each segment (any type
// with members first, q_first, end, q_scale, k_scale) norms the keys of rows [first, end) with
// k_scale and the queries of rows [q_first, end) with q_scale (q_first >= first: a pruned
// block's queries); cos/sin rows are indexed by r. Each head gives exactly what
// rms_norm_rope_heads gives it. With `items`, the segments repeat for each item (QkItems).
template <class T, class Segment, std::size_t S>
void qk_norm_rope(Context& ctx, T* qkv, std::int64_t row_stride, std::int64_t k_offset, std::int64_t heads,
                  std::int64_t head_dim, float eps, const float* cos, const float* sin,
                  const std::array<Segment, S>& segments, const QkItems& items = {}) {
  static_assert(is_device_float<T>, "qk_norm_rope takes float or bf16");
  static_assert(2 * S <= detail::kQkParts, "qk_norm_rope: at most 4 segments");
  detail::check_norm_rope_extent(0, row_stride, heads, head_dim, "qk_norm_rope");
  EPONA_CHECK(k_offset >= heads * head_dim && k_offset + heads * head_dim <= row_stride, "qk_norm_rope: key offset ",
              k_offset, " does not fit ", heads, " heads of ", head_dim, " in rows of ", row_stride);
  EPONA_CHECK(qkv != nullptr && cos != nullptr && sin != nullptr, "qk_norm_rope: null buffer or table");
  EPONA_CHECK(items.count >= 1 && items.stride >= 0 && items.rope_stride >= 0, "qk_norm_rope: ", items.count,
              " items ", items.stride, " rows apart");
  detail::QkRopeParts<T> a{qkv, row_stride, k_offset, static_cast<int>(heads), static_cast<int>(head_dim), 0, eps,
                           cos, sin, {}, {}, {}, items};
  a.start[0] = 0;
  for (const auto& s : segments) {
    EPONA_CHECK(0 <= s.first && s.first <= s.q_first && s.q_first <= s.end, "qk_norm_rope: segment rows [", s.first,
                ", ", s.end, ") with queries from ", s.q_first);
    EPONA_CHECK(s.q_scale != nullptr && s.k_scale != nullptr, "qk_norm_rope: null norm scale");
    const std::int64_t from[2] = {s.q_first, s.first};
    const float* scale[2] = {s.q_scale, s.k_scale};
    for (int kind = 0; kind < 2; ++kind, ++a.parts) {  // parts alternate q, k
      a.first[a.parts] = from[kind];
      a.scale[a.parts] = scale[kind];
      a.start[a.parts + 1] = a.start[a.parts] + (s.end - from[kind]) * heads;
    }
  }
  if (a.heads_total() == 0) return;
  if (ctx.policy().qk_norm_rope_rows && detail::row_path(ctx, a)) {  // EPONA_CUDA_QK_ROWS=0: head per warp
    detail::launch_qk_rows(ctx, a);
  } else {
    const auto kernel = detail::vector_heads(qkv, row_stride, head_dim, k_offset) ? detail::qk_norm_rope_kernel<true, T>
                                                                                : detail::qk_norm_rope_kernel<false, T>;
    detail::launch_after(kernel, detail::norm_rope_blocks(a.heads_total(), "qk_norm_rope"), detail::kNormRopeThreads, 0,
                         ctx, a);
  }
}

}  // namespace epona::cuda
