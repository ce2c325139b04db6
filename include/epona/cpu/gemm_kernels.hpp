// epona/cpu/gemm_kernels.hpp — the register-blocked GEMM micro-kernels and their panel packing:
// AVX-512 float32 (14×32 tile), AVX-512 BF16 dot products (14×32, bf16 pairs), AVX2 float32
// (6×16). Each is compiled with a target attribute, so one binary carries all of them and
// cpu_features.hpp picks at run time; no instruction beyond the build's target runs unless chosen.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <type_traits>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define EPONA_GEMM_X86 1
#endif

#include "epona/core/dtype.hpp"

#if defined(EPONA_GEMM_X86)
#define EPONA_TARGET_AVX2 __attribute__((target("avx2,fma")))
#define EPONA_TARGET_AVX512 __attribute__((target("avx512f,avx512bw,avx512dq,avx512vl,avx2,fma")))
#endif

namespace epona::cpu::gemm {

// Packed panels are arrays of 32-bit words, one "step" (a row of the panel) after another:
//   A panel (MR rows of the left operand):  a[s·MR + r]
//   B panel (NR columns of the right one):  b[s·NR + c]
// For the float32 kernels a step is one k; for the BF16 dot-product kernel it is a pair of k,
// the word holding bf16(v[2s]) in its low half and bf16(v[2s+1]) in its high half (the layout
// vdpbf16ps multiplies pairwise). Rows/columns past the operand's edge are zero.
using Word = std::uint32_t;

// Words of one pair of bf16 values (the low one first in memory, as x86 is little-endian).
inline Word bf16_pair(std::uint16_t lo, std::uint16_t hi) { return Word{lo} | (Word{hi} << 16); }

// ---- packing (portable C++: the compiler vectorises the contiguous side) -------------------

// dst[s·R + r] = f(src row r, step s0 + s) for r < rows, s < steps; zero for rows ≤ r < R.
// `step_value(const Src* row, s)` reads one step of one row (a float, a widened bf16, a pair).
template <class Src, class StepValue>
inline void pack_transposed(const Src* src, std::int64_t ld, std::int64_t rows, std::int64_t R, std::int64_t s0,
                            std::int64_t steps, Word* dst, StepValue step_value) {
  for (std::int64_t r = 0; r < rows; ++r) {
    const Src* row = src + r * ld;
    for (std::int64_t s = 0; s < steps; ++s) dst[s * R + r] = step_value(row, s0 + s);
  }
  for (std::int64_t r = rows; r < R; ++r)
    for (std::int64_t s = 0; s < steps; ++s) dst[s * R + r] = 0;
}

inline Word float_bits(float v) {
  Word w;
  std::memcpy(&w, &v, sizeof w);
  return w;
}

// One step of a float32 row as a float word; of a bf16 row widened to float.
struct FloatStep {
  Word operator()(const float* row, std::int64_t s) const { return float_bits(row[s]); }
  Word operator()(const bf16* row, std::int64_t s) const { return Word{row[s].bits} << 16; }
};

// One step of a bf16 row as a bf16 pair (k = 2s, 2s + 1; the odd one 0 past K).
struct Bf16PairStep {
  std::int64_t K;
  Word operator()(const bf16* row, std::int64_t s) const {
    const std::int64_t k = 2 * s;
    return bf16_pair(row[k].bits, k + 1 < K ? row[k + 1].bits : std::uint16_t{0});
  }
  // A float32 row rounded to bf16 (round to nearest even, as torch's autocast casts).
  Word operator()(const float* row, std::int64_t s) const {
    const std::int64_t k = 2 * s;
    return bf16_pair(bf16::from_float(row[k]), k + 1 < K ? bf16::from_float(row[k + 1]) : std::uint16_t{0});
  }
};

// dst[s·R + c] = src[(s0 + s)·ld + c] for c < cols (a row-major K×N operand: rows are steps).
inline void pack_rows(const float* src, std::int64_t ld, std::int64_t cols, std::int64_t R, std::int64_t s0,
                      std::int64_t steps, Word* dst) {
  for (std::int64_t s = 0; s < steps; ++s) {
    std::memcpy(dst + s * R, src + (s0 + s) * ld, static_cast<std::size_t>(cols) * sizeof(float));
    std::fill(dst + s * R + cols, dst + (s + 1) * R, Word{0});
  }
}

#if defined(EPONA_GEMM_X86)

// ---- AVX-512 float32: MR rows × 16·NV columns ---------------------------------------------
// Two tiles: 14×32 (28 accumulators, 2 loads + 14 broadcasts per step: light on L2, for CPUs
// with two 512-bit FMA pipes) and 6×64 (24 accumulators, 4 loads + 6 broadcasts: fewer
// broadcasts per FMA, for CPUs that split a 512-bit FMA into two 256-bit halves, as Zen 4).

inline std::uint32_t low_bits_mask(std::int64_t n) {  // n in [0, 16]
  return n >= 16 ? 0xffffu : n <= 0 ? 0u : ((1u << n) - 1u);
}

// The tile's output rows on their way to L1 while the tile is computed: C rows lie a whole
// output row apart and would otherwise miss one after another at the store.
template <int NV>
inline void prefetch_row(const float* c) {
  for (int v = 0; v < NV; ++v) _mm_prefetch(reinterpret_cast<const char*>(c + 16 * v), _MM_HINT_T0);
  _mm_prefetch(reinterpret_cast<const char*>(c + 16 * NV - 1), _MM_HINT_T0);
}

// Stores (or adds into C) the NV accumulators of one tile row; `cols` valid columns.
template <int NV>
EPONA_TARGET_AVX512 inline void store_row_avx512(float* c, const __m512* acc, std::int64_t cols, bool accumulate) {
#pragma GCC unroll 4
  for (int v = 0; v < NV; ++v) {
    const __mmask16 m = static_cast<__mmask16>(low_bits_mask(cols - 16 * v));
    __m512 x = acc[v];
    if (accumulate) x = _mm512_add_ps(x, _mm512_maskz_loadu_ps(m, c + 16 * v));
    _mm512_mask_storeu_ps(c + 16 * v, m, x);
  }
}

// Step s: acc[r][v] += A[s][r] · B[s][16v..16v+15]; `Dot` is the multiply-add of one step.
template <int MR, int NV, int Rows, class Dot>
EPONA_TARGET_AVX512 inline void micro_avx512_body(const Word* a, const Word* b, std::int64_t steps, float* c,
                                                      std::int64_t ldc, std::int64_t cols, bool accumulate, Dot dot) {
  __m512 acc[Rows][NV];
#pragma GCC unroll 14
  for (int r = 0; r < Rows; ++r) {
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) acc[r][v] = _mm512_setzero_ps();
    prefetch_row<NV>(c + r * ldc);
  }
  for (std::int64_t s = 0; s < steps; ++s) {
    __m512i bv[NV];
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) bv[v] = _mm512_load_si512(b + 16 * v);
#pragma GCC unroll 14
    for (int r = 0; r < Rows; ++r) {
      const __m512i av = _mm512_set1_epi32(static_cast<int>(a[r]));
#pragma GCC unroll 4
      for (int v = 0; v < NV; ++v) acc[r][v] = dot(acc[r][v], av, bv[v]);
    }
    a += MR;
    b += 16 * NV;
  }
#pragma GCC unroll 14
  for (int r = 0; r < Rows; ++r) store_row_avx512<NV>(c + r * ldc, acc[r], cols, accumulate);
}

struct FmaF32 {
  EPONA_TARGET_AVX512 __m512 operator()(__m512 acc, __m512i a, __m512i b) const {
    return _mm512_fmadd_ps(_mm512_castsi512_ps(a), _mm512_castsi512_ps(b), acc);
  }
};
// acc += a.lo·b.lo + a.hi·b.hi per 32-bit lane (bf16 halves, products exact, fp32 sums).
// Written as inline assembly so that the AVX-512 code around it needs no avx512bf16 target:
// nothing else in the function can then use the extension, and only the run-time dispatch
// decides whether this instruction ever executes.
struct DotBf16 {
  EPONA_TARGET_AVX512 __m512 operator()(__m512 acc, __m512i a, __m512i b) const {
    __asm__("vdpbf16ps %2, %1, %0" : "+v"(acc) : "v"(a), "v"(b));
    return acc;
  }
};

template <int MR, int NV, int Rows>
EPONA_TARGET_AVX512 void micro_avx512_f32(const Word* a, const Word* b, std::int64_t steps, float* c,
                                          std::int64_t ldc, std::int64_t cols, bool accumulate) {
  micro_avx512_body<MR, NV, Rows>(a, b, steps, c, ldc, cols, accumulate, FmaF32{});
}

// ---- AVX-512 packing: 16 rows × 16 steps at a time through an in-register transpose ------

// r[i][j] -> r[j][i] for a 16×16 block of 32-bit words.
EPONA_TARGET_AVX512 inline void transpose16x16(__m512 r[16]) {
  __m512 t[16], u[16];
  for (int p = 0; p < 8; ++p) {
    t[2 * p] = _mm512_unpacklo_ps(r[2 * p], r[2 * p + 1]);
    t[2 * p + 1] = _mm512_unpackhi_ps(r[2 * p], r[2 * p + 1]);
  }
  for (int q = 0; q < 4; ++q) {  // u[4q + c], lane L: column 4L + c of rows 4q..4q+3
    const __m512d a = _mm512_castps_pd(t[4 * q]), b = _mm512_castps_pd(t[4 * q + 2]);
    const __m512d c = _mm512_castps_pd(t[4 * q + 1]), d = _mm512_castps_pd(t[4 * q + 3]);
    u[4 * q + 0] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, b));
    u[4 * q + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, b));
    u[4 * q + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(c, d));
    u[4 * q + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(c, d));
  }
  for (int c = 0; c < 4; ++c) {
    const __m512 v = _mm512_shuffle_f32x4(u[c], u[4 + c], 0x88), w = _mm512_shuffle_f32x4(u[c], u[4 + c], 0xdd);
    const __m512 v2 = _mm512_shuffle_f32x4(u[8 + c], u[12 + c], 0x88), w2 = _mm512_shuffle_f32x4(u[8 + c], u[12 + c], 0xdd);
    r[c] = _mm512_shuffle_f32x4(v, v2, 0x88);
    r[8 + c] = _mm512_shuffle_f32x4(v, v2, 0xdd);
    r[4 + c] = _mm512_shuffle_f32x4(w, w2, 0x88);
    r[12 + c] = _mm512_shuffle_f32x4(w, w2, 0xdd);
  }
}

// How a row of the source yields 16 steps as 32-bit words (n < 16: the first n, zeros after).
struct WordRow {  // float32 values or bf16 pairs, stored as they are
  const Word* p;
  EPONA_TARGET_AVX512 __m512 load(std::int64_t s, std::int64_t n) const {
    return _mm512_maskz_loadu_ps(static_cast<__mmask16>(low_bits_mask(n)), p + s);
  }
};
struct WidenedBf16Row {  // bf16 values widened to float32
  const std::uint16_t* p;
  EPONA_TARGET_AVX512 __m512 load(std::int64_t s, std::int64_t n) const {
    const __m256i h = _mm256_maskz_loadu_epi16(static_cast<__mmask16>(low_bits_mask(n)), p + s);
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(h), 16));
  }
};

// dst[s·R + r] = row r's step s0 + s, for r < rows (zero for rows ≤ r < R), s < steps;
// `row_at(r)` gives row r's loader. Blocks of 16 rows × 16 steps.
template <class RowAt>
EPONA_TARGET_AVX512 void pack_transposed_avx512(RowAt row_at, std::int64_t rows, std::int64_t R, std::int64_t s0,
                                                std::int64_t steps, Word* dst) {
  float* out = reinterpret_cast<float*>(dst);
  for (std::int64_t g = 0; g < R; g += 16) {
    const std::int64_t group_rows = std::min<std::int64_t>(16, R - g);
    const __mmask16 lanes = static_cast<__mmask16>(low_bits_mask(group_rows));
    for (std::int64_t s = 0; s < steps; s += 16) {
      const std::int64_t n = std::min<std::int64_t>(16, steps - s);
      __m512 r[16];
      for (std::int64_t i = 0; i < 16; ++i)
        r[i] = g + i < rows ? row_at(g + i).load(s0 + s, n) : _mm512_setzero_ps();
      transpose16x16(r);
      for (std::int64_t j = 0; j < n; ++j) _mm512_mask_storeu_ps(out + (s + j) * R + g, lanes, r[j]);
    }
  }
}

// ---- AVX-512 BF16: the same tiles, one vdpbf16ps per accumulator and pair of k -----------

template <int MR, int NV, int Rows>
EPONA_TARGET_AVX512 void micro_avx512_bf16(const Word* a, const Word* b, std::int64_t steps, float* c,
                                               std::int64_t ldc, std::int64_t cols, bool accumulate) {
  micro_avx512_body<MR, NV, Rows>(a, b, steps, c, ldc, cols, accumulate, DotBf16{});
}

// A float32 row rounded to bf16 pairs with vcvtne2ps2bf16 (round to nearest even, as torch's
// autocast casts), 32 values at a time: out[s] = pair(x[2s], x[2s+1]), the odd tail zero.
// Inline assembly for the reason given at DotBf16.
EPONA_TARGET_AVX512 inline void round_row_to_bf16_pairs(const float* x, std::int64_t K, Word* out) {
  std::int64_t k = 0;
  for (; k + 32 <= K; k += 32) {
    const __m512 lo = _mm512_loadu_ps(x + k), hi = _mm512_loadu_ps(x + k + 16);
    __m512i pairs;
    __asm__("vcvtne2ps2bf16 %2, %1, %0" : "=v"(pairs) : "v"(hi), "v"(lo));
    _mm512_storeu_si512(out + k / 2, pairs);
  }
  for (; k < K; k += 2)
    out[k / 2] = bf16_pair(bf16::from_float(x[k]), k + 1 < K ? bf16::from_float(x[k + 1]) : std::uint16_t{0});
}

// An A panel (R <= 16 rows: the kernel's MR) of bf16 pairs rounded from float32 rows (x rows
// ld apart, K columns): each row's steps [s0, s0 + steps) rounded with vcvtne2ps2bf16 into a
// scratch row, then transposed.
EPONA_TARGET_AVX512 inline void pack_bf16_pairs_rounded(const float* x, std::int64_t ld, std::int64_t rows,
                                                            std::int64_t R, std::int64_t K, std::int64_t s0,
                                                            std::int64_t steps, Word* dst) {
  constexpr std::int64_t kMaxRows = 16, kMaxSteps = 256;
  alignas(64) Word rounded[kMaxRows * kMaxSteps];
  for (std::int64_t st = 0; st < steps; st += kMaxSteps) {  // steps <= kc in practice: one pass
    const std::int64_t n = std::min(kMaxSteps, steps - st), k0 = 2 * (s0 + st);
    for (std::int64_t r = 0; r < rows; ++r)
      round_row_to_bf16_pairs(x + r * ld + k0, std::min<std::int64_t>(2 * n, K - k0), rounded + r * kMaxSteps);
    pack_transposed_avx512([&](std::int64_t r) { return WordRow{rounded + r * kMaxSteps}; }, rows, R, 0, n,
                           dst + st * R);
  }
}

// Float32 rows, bf16 rows widened, bf16 rows as pairs (K even: a pair is one aligned word).
inline void pack_f32_avx512(const float* src, std::int64_t ld, std::int64_t rows, std::int64_t R, std::int64_t s0,
                            std::int64_t steps, Word* dst) {
  pack_transposed_avx512([&](std::int64_t r) { return WordRow{reinterpret_cast<const Word*>(src + r * ld)}; }, rows,
                         R, s0, steps, dst);
}
inline void pack_bf16_widened_avx512(const bf16* src, std::int64_t ld, std::int64_t rows, std::int64_t R,
                                     std::int64_t s0, std::int64_t steps, Word* dst) {
  pack_transposed_avx512(
      [&](std::int64_t r) { return WidenedBf16Row{reinterpret_cast<const std::uint16_t*>(src + r * ld)}; }, rows, R,
      s0, steps, dst);
}
inline void pack_bf16_pairs_avx512(const bf16* src, std::int64_t K, std::int64_t rows, std::int64_t R,
                                   std::int64_t s0, std::int64_t steps, Word* dst) {
  pack_transposed_avx512([&](std::int64_t r) { return WordRow{reinterpret_cast<const Word*>(src + r * K)}; }, rows,
                         R, s0, steps, dst);
}

// ---- AVX2 float32: 6 rows × 16 columns (12 accumulators) ------------------------------------

EPONA_TARGET_AVX2 inline void store_row_avx2(float* c, __m256 v0, __m256 v1, std::int64_t cols, bool accumulate) {
  if (cols == 16) {
    if (accumulate) {
      v0 = _mm256_add_ps(v0, _mm256_loadu_ps(c));
      v1 = _mm256_add_ps(v1, _mm256_loadu_ps(c + 8));
    }
    _mm256_storeu_ps(c, v0);
    _mm256_storeu_ps(c + 8, v1);
    return;
  }
  alignas(32) float tmp[16];
  _mm256_store_ps(tmp, v0);
  _mm256_store_ps(tmp + 8, v1);
  for (std::int64_t j = 0; j < cols; ++j) c[j] = accumulate ? c[j] + tmp[j] : tmp[j];
}

template <int Rows>
EPONA_TARGET_AVX2 void micro_avx2_f32(const Word* a, const Word* b, std::int64_t steps, float* c, std::int64_t ldc,
                                      std::int64_t cols, bool accumulate) {
  constexpr int MR = 6, NR = 16;
  __m256 acc0[Rows], acc1[Rows];
#pragma GCC unroll 6
  for (int r = 0; r < Rows; ++r) acc0[r] = acc1[r] = _mm256_setzero_ps();
  const float* ap = reinterpret_cast<const float*>(a);
  const float* bp = reinterpret_cast<const float*>(b);
  for (std::int64_t s = 0; s < steps; ++s) {
    const __m256 b0 = _mm256_load_ps(bp), b1 = _mm256_load_ps(bp + 8);
#pragma GCC unroll 6
    for (int r = 0; r < Rows; ++r) {
      const __m256 av = _mm256_broadcast_ss(ap + r);
      acc0[r] = _mm256_fmadd_ps(av, b0, acc0[r]);
      acc1[r] = _mm256_fmadd_ps(av, b1, acc1[r]);
    }
    ap += MR;
    bp += NR;
  }
#pragma GCC unroll 6
  for (int r = 0; r < Rows; ++r) store_row_avx2(c + r * ldc, acc0[r], acc1[r], cols, accumulate);
}

#endif  // EPONA_GEMM_X86

// ---- AMX BF16 (opt-in): a 32×32 tile of C in four 16×16 fp32 tiles ------------------------
// A panels as [row][step] (a tile row is 16 pairs of one row of A), B panels as everywhere
// (a tile row is one step of 16 columns). Per 16 steps: 2 A tiles, 2 B tiles, 4 tdpbf16ps.
// The tile operations come from a policy: AmxTiles (the instructions, inline assembly) or an
// emulation written from the instruction's definition, which the tests run on any CPU to
// check this kernel's data layout and edges.

// The A panel of AMX: rows [0, rows) of float32 x (ld apart) rounded to bf16 pairs for steps
// [s0, s0 + steps) (K columns; pairs past K are zero), as [row][step]; rows up to R zero.
inline void pack_bf16_pairs_rows(const float* x, std::int64_t ld, std::int64_t rows, std::int64_t R, std::int64_t K,
                                 std::int64_t s0, std::int64_t steps, Word* dst, bool avx512) {
  const std::int64_t k0 = 2 * s0, n = std::clamp<std::int64_t>(K - k0, 0, 2 * steps), words = (n + 1) / 2;
  for (std::int64_t r = 0; r < R; ++r) {
    Word* out = dst + r * steps;
    std::int64_t done = 0;
    if (r < rows) {
#if defined(EPONA_GEMM_X86)
      if (avx512) round_row_to_bf16_pairs(x + r * ld + k0, n, out), done = words;
#endif
      for (; done < words; ++done) out[done] = Bf16PairStep{K}(x + r * ld, s0 + done);
    }
    std::fill(out + done, out + steps, Word{0});
  }
}

template <class Tiles, int Rows>
void micro_amx(const Word* a, const Word* b, std::int64_t steps, float* c, std::int64_t ldc, std::int64_t cols,
               bool accumulate) {
  constexpr std::int64_t kNR = 32;
  Tiles t;
  t.configure();
  const bool full = Rows == 32 && cols == 32;
  alignas(64) float edge[32 * 32];  // the C tile when it is not whole (edge rows or columns)
  if (!full) {
    for (int r = 0; r < 32; ++r)
      for (int j = 0; j < 32; ++j) edge[r * 32 + j] = accumulate && r < Rows && j < cols ? c[r * ldc + j] : 0.f;
  }
  float* cbase = full ? c : edge;
  const std::int64_t cstride = (full ? ldc : 32) * 4;
  if (accumulate || !full) {
    t.template load<0>(cbase, cstride);
    t.template load<1>(cbase + 16, cstride);
    t.template load<2>(cbase + 16 * cstride / 4, cstride);
    t.template load<3>(cbase + 16 * cstride / 4 + 16, cstride);
  } else {
    t.template zero<0>();
    t.template zero<1>();
    t.template zero<2>();
    t.template zero<3>();
  }
  const std::int64_t astride = steps * 4;
  for (std::int64_t s = 0; s < steps; s += 16) {
    t.template load<4>(a + s, astride);
    t.template load<5>(a + 16 * steps + s, astride);
    t.template load<6>(b + s * kNR, kNR * 4);
    t.template load<7>(b + s * kNR + 16, kNR * 4);
    t.template dot<0, 4, 6>();
    t.template dot<1, 4, 7>();
    t.template dot<2, 5, 6>();
    t.template dot<3, 5, 7>();
  }
  t.template store<0>(cbase, cstride);
  t.template store<1>(cbase + 16, cstride);
  t.template store<2>(cbase + 16 * cstride / 4, cstride);
  t.template store<3>(cbase + 16 * cstride / 4 + 16, cstride);
  t.release();
  if (!full)
    for (int r = 0; r < Rows; ++r)
      for (std::int64_t j = 0; j < cols; ++j) c[r * ldc + j] = edge[r * 32 + j];
}

#if defined(EPONA_GEMM_X86)
// The AMX instructions. Every tile: 16 rows of 64 bytes (fp32 C, bf16 A, bf16-pair B).
struct AmxTiles {
  static void configure() {
    alignas(64) std::uint8_t cfg[64] = {};
    cfg[0] = 1;  // palette 1
    for (int i = 0; i < 8; ++i) {
      cfg[16 + 2 * i] = 64;  // bytes per row (little-endian uint16)
      cfg[48 + i] = 16;      // rows
    }
    __asm__ volatile("ldtilecfg %0" : : "m"(cfg));
  }
  static void release() { __asm__ volatile("tilerelease" ::); }
#define EPONA_AMX_TILE_OPS(T)                                                                                   \
  void load_##T(const void* p, std::int64_t stride) {                                                          \
    __asm__ volatile("tileloadd (%0,%1,1), %%tmm" #T : : "r"(p), "r"(stride) : "memory");                      \
  }                                                                                                             \
  void store_##T(void* p, std::int64_t stride) {                                                                \
    __asm__ volatile("tilestored %%tmm" #T ", (%0,%1,1)" : : "r"(p), "r"(stride) : "memory");                  \
  }
  EPONA_AMX_TILE_OPS(0)
  EPONA_AMX_TILE_OPS(1)
  EPONA_AMX_TILE_OPS(2)
  EPONA_AMX_TILE_OPS(3)
  EPONA_AMX_TILE_OPS(4)
  EPONA_AMX_TILE_OPS(5)
  EPONA_AMX_TILE_OPS(6)
  EPONA_AMX_TILE_OPS(7)
#undef EPONA_AMX_TILE_OPS
  template <int T>
  void load(const void* p, std::int64_t stride) {
    if constexpr (T == 0) load_0(p, stride);
    else if constexpr (T == 1) load_1(p, stride);
    else if constexpr (T == 2) load_2(p, stride);
    else if constexpr (T == 3) load_3(p, stride);
    else if constexpr (T == 4) load_4(p, stride);
    else if constexpr (T == 5) load_5(p, stride);
    else if constexpr (T == 6) load_6(p, stride);
    else load_7(p, stride);
  }
  template <int T>
  void store(void* p, std::int64_t stride) {
    static_assert(T < 4, "only the C tiles are stored");
    if constexpr (T == 0) store_0(p, stride);
    else if constexpr (T == 1) store_1(p, stride);
    else if constexpr (T == 2) store_2(p, stride);
    else store_3(p, stride);
  }
  template <int T>
  void zero() {
    if constexpr (T == 0) __asm__ volatile("tilezero %%tmm0" ::);
    else if constexpr (T == 1) __asm__ volatile("tilezero %%tmm1" ::);
    else if constexpr (T == 2) __asm__ volatile("tilezero %%tmm2" ::);
    else __asm__ volatile("tilezero %%tmm3" ::);
  }
  // C += A·B (AT&T order: B, A, C).
  template <int C, int A, int B>
  void dot() {
    if constexpr (C == 0) __asm__ volatile("tdpbf16ps %%tmm6, %%tmm4, %%tmm0" ::);
    else if constexpr (C == 1) __asm__ volatile("tdpbf16ps %%tmm7, %%tmm4, %%tmm1" ::);
    else if constexpr (C == 2) __asm__ volatile("tdpbf16ps %%tmm6, %%tmm5, %%tmm2" ::);
    else __asm__ volatile("tdpbf16ps %%tmm7, %%tmm5, %%tmm3" ::);
    static_assert((C == 0 && A == 4 && B == 6) || (C == 1 && A == 4 && B == 7) || (C == 2 && A == 5 && B == 6) ||
                      (C == 3 && A == 5 && B == 7),
                  "the kernel's four products only");
  }
};
#endif

// A micro-kernel: C[rows × cols] (+)= A panel · B panel over `steps` steps.
using MicroKernel = void (*)(const Word* a, const Word* b, std::int64_t steps, float* c, std::int64_t ldc,
                             std::int64_t cols, bool accumulate);

// One kernel family: its tile and one compiled micro-kernel per row count 1..MR (the last
// panel of an operand whose rows are not a multiple of MR runs the narrower one: no wasted FMAs).
struct KernelFamily {
  int mr = 0, nr = 0;
  bool avx512_packing = false;  // pack with the AVX-512 transposes (else portable loops)
  int k_per_step = 1;     // 2 for bf16 pairs
  std::int64_t kc = 256;  // steps per K block: an A micro-panel (MR×kc) stays in L1
  std::int64_t nc = 256;  // columns per B block: a kc×nc block stays in L2
  MicroKernel micro[32] = {};
  std::int64_t k_align = 1;    // K blocks hold a multiple of this many steps (AMX: 16)
  bool a_rows_major = false;   // A panels as [row][step] (AMX tiles) instead of [step][row]
  MicroKernel for_rows(std::int64_t rows) const { return micro[rows - 1]; }
};

#if defined(EPONA_GEMM_X86)
namespace detail {
// MR × NV vectors of `lanes` floats per row.
template <template <int, int, int> class Kernel, int MR, int NV, int... R>
KernelFamily make_family(int lanes, int k_per_step, std::int64_t nc, bool avx512_packing,
                         std::integer_sequence<int, R...>) {
  KernelFamily f{MR, lanes * NV, avx512_packing, k_per_step, 256, nc, {}};
  ((f.micro[R] = Kernel<MR, NV, R + 1>::run), ...);
  return f;
}
// Adapters giving the kernel templates one shape (template <MR, NV, Rows> with ::run).
template <int MR, int NV, int Rows>
struct Avx512F32 {
  static constexpr MicroKernel run = &micro_avx512_f32<MR, NV, Rows>;
};
template <int MR, int NV, int Rows>
struct Avx512Bf16 {
  static constexpr MicroKernel run = &micro_avx512_bf16<MR, NV, Rows>;
};
template <int MR, int NV, int Rows>
struct Avx2F32 {
  static_assert(NV == 2, "the AVX2 tile is 16 columns (two ymm)");
  static constexpr MicroKernel run = &micro_avx2_f32<Rows>;
};
}  // namespace detail

// Tile shapes: Tall = 14×32, Wide = 6×64 (see the AVX-512 section).
enum class Tile { Tall, Wide };

inline const KernelFamily& avx512_f32(Tile t) {
  static const KernelFamily tall =
      detail::make_family<detail::Avx512F32, 14, 2>(16, 1, 256, true, std::make_integer_sequence<int, 14>{});
  static const KernelFamily wide =
      detail::make_family<detail::Avx512F32, 6, 4>(16, 1, 256, true, std::make_integer_sequence<int, 6>{});
  return t == Tile::Tall ? tall : wide;
}
inline const KernelFamily& avx512_bf16(Tile t) {
  static const KernelFamily tall =
      detail::make_family<detail::Avx512Bf16, 14, 2>(16, 2, 256, true, std::make_integer_sequence<int, 14>{});
  static const KernelFamily wide =
      detail::make_family<detail::Avx512Bf16, 6, 4>(16, 2, 256, true, std::make_integer_sequence<int, 6>{});
  return t == Tile::Tall ? tall : wide;
}
// The AMX family with a given tile policy (AmxTiles on the CPU; an emulation in the tests).
template <class Tiles, int... R>
KernelFamily make_amx_family(std::integer_sequence<int, R...>) {
  KernelFamily f{32, 32, true, 2, 512, 256, {}};  // 1024 k per call: amortises ldtilecfg and the C tiles
  ((f.micro[R] = &micro_amx<Tiles, R + 1>), ...);
  f.k_align = 16;
  f.a_rows_major = true;
  return f;
}
inline const KernelFamily& amx_bf16() {
  static const KernelFamily f = make_amx_family<AmxTiles>(std::make_integer_sequence<int, 32>{});
  return f;
}

inline const KernelFamily& avx2_f32() {
  static const KernelFamily f =
      detail::make_family<detail::Avx2F32, 6, 2>(8, 1, 128, false, std::make_integer_sequence<int, 6>{});
  return f;
}
#endif

}  // namespace epona::cpu::gemm
