// epona/cpu/attention.hpp — scaled-dot-product attention over strided, token-major data:
// softmax(q kᵀ · scale + mask) v per sequence and head, flash-style: one tile of queries
// walks the keys tile by tile with an online softmax, so no more than a tile of scores ever
// exists. Strides let callers attend straight out of packed QKV buffers and across frames
// (the MST's temporal attention) without transposes. Head dim 128 (and 64) is compiled in.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "epona/core/error.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

using epona::AttentionShape;
using epona::Mask;
// (core/kernel_options.hpp.) A query that sees no key (all −inf) gets a zero output, never NaN.

namespace detail::attn {

using simd::Batch;
inline constexpr std::int64_t kW = simd::kWidth;
// Query tile: QV SIMD vectors of queries side by side (queries live in the lanes while the
// scores are computed, so the softmax statistics are plain vector ops): 2 vectors, or 1 when
// a sequence is that short (the MST's temporal attention over 10 frames). Key tile: kTileK.
inline constexpr int kMaxQV = 2;
inline constexpr std::int64_t kMaxTileQ = kMaxQV * kW;
inline constexpr std::int64_t kTileK = 64;
// Register blocking of the two micro-kernels (32 vector registers with AVX-512, 16 without).
inline constexpr int kScoreKeys = kW >= 16 ? 8 : 4;   // keys per score block with 2 query vectors
inline constexpr int kPvRows = 4;                     // query rows per P·V block
inline constexpr int kPvVecs = kW >= 16 ? 4 : 2;      // head-dim vectors per P·V block
inline constexpr float kNegInf = -std::numeric_limits<float>::infinity();

inline std::int64_t round_up(std::int64_t n, std::int64_t m) { return (n + m - 1) / m * m; }

// One thread's scratch, allocated once per call: the query tile transposed (d, query), one
// tile of scores (key, query), the running output (query, d), running max / sum / rescale
// factors, V rows padded to whole vectors when head_dim is not a multiple of kW, and the
// keys of a partial score block.
struct Scratch {
  std::int64_t dim, dpad;
  simd::AlignedFloats qt, st, out, m, l, alpha, vpad, kspare;
  Scratch(std::int64_t dim_, std::int64_t dpad_)
      : dim(dim_), dpad(dpad_), qt(dim_ * kMaxTileQ), st(kTileK * kMaxTileQ), out(kMaxTileQ * dpad_),
        m(kMaxTileQ), l(kMaxTileQ), alpha(kMaxTileQ), vpad(dim_ == dpad_ ? 0 : kTileK * dpad_),
        kspare(kScoreKeys * kMaxQV * dim_) {}
};

// Where one (sequence, head, query tile) reads and writes.
struct TileRef {
  const float *q, *k, *v;  // row 0 of this sequence and head
  float* o;
  std::int64_t q0, nq;     // first query of the tile, queries in it
};

template <int QV>
inline void pack_queries(const AttentionShape& a, const TileRef& t, Scratch& w) {
  constexpr std::int64_t kTileQ = QV * kW;
  if (t.nq < kTileQ) std::fill_n(w.qt.data(), w.dim * kTileQ, 0.f);  // padding lanes score 0
  for (std::int64_t i = 0; i < t.nq; ++i) {
    const float* qi = t.q + (t.q0 + i) * a.q_row;
    for (std::int64_t d = 0; d < w.dim; ++d) w.qt[d * kTileQ + i] = qi[d];
  }
}

// st[jj, :] = scale · (k_{j0+jj} · q_i) for JB keys (rows k_row apart) and all queries of
// the tile; only the first nvalid rows are stored.
template <int D, int QV, int JB>
inline void score_block(const float* qt, const float* k0, std::int64_t k_row, std::int64_t dim, float scale,
                        float* st, int nvalid = JB) {
  constexpr std::int64_t kTileQ = QV * kW;
  const std::int64_t n = D > 0 ? D : dim;
  Batch acc[JB][QV];
  for (int jj = 0; jj < JB; ++jj)
    for (int v = 0; v < QV; ++v) acc[jj][v] = Batch(0.f);
  for (std::int64_t d = 0; d < n; ++d) {
    Batch qv[QV];
    for (int v = 0; v < QV; ++v) qv[v] = Batch::load_aligned(qt + d * kTileQ + v * kW);
    for (int jj = 0; jj < JB; ++jj) {
      const Batch kd(k0[jj * k_row + d]);
      for (int v = 0; v < QV; ++v) acc[jj][v] = xsimd::fma(kd, qv[v], acc[jj][v]);
    }
  }
  const Batch sc(scale);
  for (int jj = 0; jj < nvalid; ++jj)
    for (int v = 0; v < QV; ++v) (acc[jj][v] * sc).store_aligned(st + jj * kTileQ + v * kW);
}

// Keys [j, nk) of the tile in blocks of JB, the remainder in blocks of JB/2, JB/4, .. 4; the
// last partial block of 4 (one accumulator chain alone would wait on the FMA latency) has its
// rows copied to `spare` with the last key repeated to fill the block.
template <int D, int QV, int JB>
inline void score_keys(const float* qt, const float* kb, std::int64_t k_row, std::int64_t dim, float scale, float* st,
                       std::int64_t j, std::int64_t nk, float* spare) {
  constexpr std::int64_t kTileQ = QV * kW;
  for (; j + JB <= nk; j += JB) score_block<D, QV, JB>(qt, kb + j * k_row, k_row, dim, scale, st + j * kTileQ);
  const auto rest = static_cast<int>(nk - j);
  if (rest == 0) return;
  if constexpr (JB > 4) {
    return score_keys<D, QV, JB / 2>(qt, kb, k_row, dim, scale, st, j, nk, spare);
  }
  for (int jj = 0; jj < JB; ++jj) std::copy_n(kb + (j + std::min(jj, rest - 1)) * k_row, dim, spare + jj * dim);
  score_block<D, QV, JB>(qt, spare, dim, dim, scale, st + j * kTileQ, rest);
}

template <int D, int QV>
inline void score_tile(const AttentionShape& a, const TileRef& t, std::int64_t k0, std::int64_t nk, float scale,
                       Scratch& w) {
  constexpr int kKeys = kScoreKeys * kMaxQV / QV;  // same register budget for either tile
  score_keys<D, QV, kKeys>(w.qt.data(), t.k + k0 * a.k_row, a.k_row, w.dim, scale, w.st.data(), 0, nk,
                           w.kspare.data());
}

// Adds the additive mask and applies causality to the tile of scores.
template <int QV>
inline void mask_tile(const AttentionShape& a, const TileRef& t, std::int64_t k0, std::int64_t nk, Scratch& w) {
  constexpr std::int64_t kTileQ = QV * kW;
  if (a.additive_mask)
    for (std::int64_t i = 0; i < t.nq; ++i) {
      const float* mrow = a.additive_mask + (t.q0 + i) * a.lk + k0;
      for (std::int64_t j = 0; j < nk; ++j) w.st[j * kTileQ + i] += mrow[j];
    }
  if (a.mask == Mask::Causal && k0 + nk - 1 > t.q0)
    for (std::int64_t j = 0; j < nk; ++j)
      for (std::int64_t i = 0; i < kTileQ && t.q0 + i < k0 + j; ++i) w.st[j * kTileQ + i] = kNegInf;
}

// Online softmax over one tile: new running max, scores -> exp(score - max), running sum
// rescaled, and alpha = exp(old max - new max) for rescaling the running output. While a
// query has seen only −inf its max stays −inf and exp is taken against 0, so nothing is NaN.
template <int QV>
inline void softmax_tile(std::int64_t nk, Scratch& w) {
  constexpr std::int64_t kTileQ = QV * kW;
  for (std::int64_t v = 0; v < QV; ++v) {
    float* st = w.st.data() + v * kW;
    const Batch m_old = Batch::load_aligned(w.m.data() + v * kW);
    Batch m_new = m_old;
    for (std::int64_t j = 0; j < nk; ++j) m_new = xsimd::max(m_new, Batch::load_aligned(st + j * kTileQ));
    const Batch base = xsimd::select(m_new == Batch(kNegInf), Batch(0.f), m_new);
    Batch sum(0.f);
    for (std::int64_t j = 0; j < nk; ++j) {
      const Batch p = xsimd::exp(Batch::load_aligned(st + j * kTileQ) - base);
      p.store_aligned(st + j * kTileQ);
      sum += p;
    }
    const Batch alpha = xsimd::exp(m_old - base);
    alpha.store_aligned(w.alpha.data() + v * kW);
    (Batch::load_aligned(w.l.data() + v * kW) * alpha + sum).store_aligned(w.l.data() + v * kW);
    m_new.store_aligned(w.m.data() + v * kW);
  }
}

// out[i0..i0+kPvRows, d0..d0+NV·kW) = alpha_i · out + Σ_j p[j, i] · v_j over the tile's keys.
template <int QV, int NV>
inline void pv_block(const Scratch& w, const float* vb, std::int64_t v_stride, std::int64_t nk, std::int64_t i0,
                     std::int64_t d0) {
  constexpr std::int64_t kTileQ = QV * kW;
  Batch acc[kPvRows][NV];
  for (int r = 0; r < kPvRows; ++r) {
    const Batch al(w.alpha[i0 + r]);
    for (int c = 0; c < NV; ++c) acc[r][c] = Batch::load_aligned(w.out.data() + (i0 + r) * w.dpad + d0 + c * kW) * al;
  }
  for (std::int64_t j = 0; j < nk; ++j) {
    Batch vv[NV];
    for (int c = 0; c < NV; ++c) vv[c] = simd::load_reused(vb + j * v_stride + d0 + c * kW);
    for (int r = 0; r < kPvRows; ++r) {
      const Batch p(w.st[j * kTileQ + i0 + r]);
      for (int c = 0; c < NV; ++c) acc[r][c] = xsimd::fma(p, vv[c], acc[r][c]);
    }
  }
  for (int r = 0; r < kPvRows; ++r)
    for (int c = 0; c < NV; ++c) acc[r][c].store_aligned(w.out.data() + (i0 + r) * w.dpad + d0 + c * kW);
}

template <int D, int QV>
inline void pv_tile(const AttentionShape& a, const TileRef& t, std::int64_t k0, std::int64_t nk, Scratch& w) {
  const std::int64_t dpad = D > 0 && D % kW == 0 ? D : w.dpad;
  const float* vb = t.v + k0 * a.v_row;
  std::int64_t v_stride = a.v_row;
  if (w.dim != dpad) {  // head_dim not a multiple of kW: copy V rows into zero-padded rows
    for (std::int64_t j = 0; j < nk; ++j) {
      std::copy_n(vb + j * a.v_row, w.dim, w.vpad.data() + j * dpad);
      std::fill(w.vpad.data() + j * dpad + w.dim, w.vpad.data() + (j + 1) * dpad, 0.f);
    }
    vb = w.vpad.data();
    v_stride = dpad;
  }
  const std::int64_t rows = round_up(t.nq, kPvRows);
  for (std::int64_t i0 = 0; i0 < rows; i0 += kPvRows) {
    std::int64_t d0 = 0;
    for (; d0 + kPvVecs * kW <= dpad; d0 += kPvVecs * kW) pv_block<QV, kPvVecs>(w, vb, v_stride, nk, i0, d0);
    for (; d0 < dpad; d0 += kW) pv_block<QV, 1>(w, vb, v_stride, nk, i0, d0);
  }
}

inline void write_output(const AttentionShape& a, const TileRef& t, const Scratch& w) {
  for (std::int64_t i = 0; i < t.nq; ++i) {
    const float l = w.l[i];
    const Batch inv(l > 0 ? 1.0f / l : 0.f);
    simd::map(w.dim, t.o + (t.q0 + i) * a.o_row, [inv](const Batch& x) { return x * inv; },
              w.out.data() + i * w.dpad);
  }
}

template <int D, int QV>
inline void attend_tile(const AttentionShape& a, const TileRef& t, float scale, Scratch& w) {
  constexpr std::int64_t kTileQ = QV * kW;
  pack_queries<QV>(a, t, w);
  std::fill_n(w.m.data(), kTileQ, kNegInf);
  std::fill_n(w.l.data(), kTileQ, 0.f);
  std::fill_n(w.out.data(), kTileQ * w.dpad, 0.f);
  // Causal: keys beyond the tile's last query are never seen.
  const std::int64_t nkeys = a.mask == Mask::Causal ? std::min(a.lk, t.q0 + t.nq) : a.lk;
  for (std::int64_t k0 = 0; k0 < nkeys; k0 += kTileK) {
    const std::int64_t nk = std::min(kTileK, nkeys - k0);
    score_tile<D, QV>(a, t, k0, nk, scale, w);
    mask_tile<QV>(a, t, k0, nk, w);
    softmax_tile<QV>(nk, w);
    pv_tile<D, QV>(a, t, k0, nk, w);
  }
  write_output(a, t, w);
}

template <int D, int QV>
inline void attention_impl(const float* q, const float* k, const float* v, float* o, const AttentionShape& a) {
  constexpr std::int64_t kTileQ = QV * kW;
  const float scale = a.scale != 0 ? a.scale : 1.0f / std::sqrt(static_cast<float>(a.head_dim));
  const std::int64_t dim = a.head_dim, dpad = round_up(dim, kW);
  const std::int64_t qtiles = (a.lq + kTileQ - 1) / kTileQ;
  const std::int64_t tasks = a.seqs * a.heads * qtiles;
  const double work = static_cast<double>(a.seqs * a.heads) * static_cast<double>(a.lq) * static_cast<double>(a.lk) *
                      static_cast<double>(dim);
#pragma omp parallel if (tasks > 1 && work > 1e5)
  {
    Scratch w(dim, dpad);
#pragma omp for schedule(dynamic)
    for (std::int64_t task = 0; task < tasks; ++task) {
      const std::int64_t s = task / (a.heads * qtiles), h = task / qtiles % a.heads, qt = task % qtiles;
      const std::int64_t col = h * dim;
      const TileRef t{q + s * a.q_seq + col, k + s * a.k_seq + col, v + s * a.v_seq + col, o + s * a.o_seq + col,
                      qt * kTileQ, std::min(kTileQ, a.lq - qt * kTileQ)};
      attend_tile<D, QV>(a, t, scale, w);
    }
  }
}

inline void check_shape(const AttentionShape& a) {
  EPONA_CHECK(a.seqs >= 0 && a.heads >= 0 && a.lq >= 0 && a.lk >= 0, "attention: negative extent (seqs ", a.seqs,
              ", heads ", a.heads, ", lq ", a.lq, ", lk ", a.lk, ")");
  EPONA_CHECK(a.head_dim > 0, "attention: head_dim must be positive, got ", a.head_dim);
}

}  // namespace detail::attn

// o = softmax(q kᵀ · scale + mask) v for every sequence and head (see AttentionShape).
inline void attention(Context&, const float* q, const float* k, const float* v, float* o, const AttentionShape& a) {
  using namespace detail::attn;
  check_shape(a);
  const bool short_seq = a.lq <= kW;  // one vector of queries per tile suffices
  switch (a.head_dim) {
    case 128: short_seq ? attention_impl<128, 1>(q, k, v, o, a) : attention_impl<128, 2>(q, k, v, o, a); break;
    case 64: short_seq ? attention_impl<64, 1>(q, k, v, o, a) : attention_impl<64, 2>(q, k, v, o, a); break;
    default: short_seq ? attention_impl<0, 1>(q, k, v, o, a) : attention_impl<0, 2>(q, k, v, o, a); break;
  }
}

}  // namespace epona::cpu
