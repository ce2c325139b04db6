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
  MicroKernel micro[16] = {};
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
inline const KernelFamily& avx2_f32() {
  static const KernelFamily f =
      detail::make_family<detail::Avx2F32, 6, 2>(8, 1, 128, false, std::make_integer_sequence<int, 6>{});
  return f;
}
#endif

}  // namespace epona::cpu::gemm
