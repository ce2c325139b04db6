// epona/cpu/gemm.hpp — Linear layers on the CPU: y = act(x · Wᵀ + b) with PyTorch's weight
// layout W (out, in). Packed, cache-blocked micro-kernels (gemm_kernels.hpp, chosen at run time
// by cpu_features.hpp: AMX tiles or AVX512-BF16 dot products for bf16 weights, AVX-512, AVX2)
// with bias and activation applied to each finished tile; Eigen where no kernel fits (generic).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string_view>
#include <type_traits>
#include <vector>

#include "epona/cpu/context.hpp"  // first: includes Eigen with GCC 12's false positives silenced
#include "epona/core/kernel_options.hpp"
#include "epona/cpu/activation.hpp"
#include "epona/cpu/cpu_features.hpp"
#include "epona/cpu/gemm_driver.hpp"
#include "epona/cpu/gemm_kernels.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

using epona::Epilogue;

namespace detail {
using RowMat = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using Strided = Eigen::OuterStride<>;
using MapRow = Eigen::Map<RowMat, Eigen::Unaligned, Strided>;
using CMapRow = Eigen::Map<const RowMat, Eigen::Unaligned, Strided>;

// bf16 -> float is a 16-bit shift; a plain loop the compiler vectorises.
inline void widen_bf16(const bf16* src, float* dst, std::int64_t n) {
  for (std::int64_t i = 0; i < n; ++i) {
    const std::uint32_t u = static_cast<std::uint32_t>(src[i].bits) << 16;
    std::memcpy(dst + i, &u, sizeof u);
  }
}

// Per-thread grow-only float buffers for the small per-call copies of linear (the widened bf16
// bias, the split rows of the dot-product path): no allocation per call once they have grown.
enum class ScratchSlot { Bias = 0, SplitRows = 1 };
inline float* scratch_floats(ScratchSlot slot, std::int64_t n) {
  thread_local std::vector<float> buffers[2];
  auto& b = buffers[static_cast<int>(slot)];
  if (static_cast<std::int64_t>(b.size()) < n) b.resize(static_cast<std::size_t>(n));
  return b.data();
}

struct Identity {
  simd::Batch operator()(const simd::Batch& x) const { return x; }
};

// y[m, :] = act(y[m, :] + bias) over rows of width n (row stride ldy); bias may be null.
template <class Act>
inline void bias_activation_row(float* yr, std::int64_t n, const float* bias, Act act) {
  using simd::Batch;
  if (bias) simd::map(n, yr, [act](const Batch& v, const Batch& b) { return act(v + b); }, yr, bias);
  else simd::map(n, yr, act, yr);
}

// Calls f(act) with the epilogue's batch functor (None is the identity, used for a bias alone).
template <class F>
inline void with_activation(Epilogue e, F&& f) {
  switch (e) {
    case Epilogue::None: f(Identity{}); break;
    case Epilogue::GeluErf: f(act::GeluErf{}); break;
    case Epilogue::GeluTanh: f(act::GeluTanh{}); break;
    case Epilogue::Silu: f(act::Silu{}); break;
  }
}

// The epilogue over a (rows, n) block, rows in parallel when `parallel` (and the block is large).
inline void apply_epilogue(float* y, std::int64_t ldy, std::int64_t rows, std::int64_t n, const float* bias,
                           Epilogue e, bool parallel = true) {
  if (e == Epilogue::None && !bias) return;
  with_activation(e, [&](auto act) {
    if (parallel) simd::for_each_row(rows, n, [=](std::int64_t r) { bias_activation_row(y + r * ldy, n, bias, act); });
    else
      for (std::int64_t r = 0; r < rows; ++r) bias_activation_row(y + r * ldy, n, bias, act);
  });
}

// Kept for callers of the first version: the epilogue alone on a contiguous buffer.
inline void apply_epilogue(Context&, float* y, std::int64_t n, Epilogue e) {
  with_activation(e, [&](auto act) { simd::parallel_map(n, y, act, y); });
}

// Up to this many rows, one pass over the weights with dot products beats any GEMM: the
// product is bound by reading the weights (adaLN modulation and embedders on a batch of 1-2).
inline constexpr int kDotRows = 4;

// y[m, n] = x[m, :] · w[n, :] for m < M <= kDotRows and n in [n0, n1), fp32 weights.
inline void dot_rows(const float* x, std::int64_t ldx, const float* w, float* y, std::int64_t ldy, std::int64_t M,
                     std::int64_t n0, std::int64_t n1, std::int64_t K) {
  using simd::Batch;
  constexpr std::int64_t W = simd::kWidth;
  for (std::int64_t n = n0; n < n1; ++n) {
    const float* wn = w + n * K;
    Batch acc[kDotRows] = {Batch(0.f), Batch(0.f), Batch(0.f), Batch(0.f)};
    std::int64_t k = 0;
    for (; k + W <= K; k += W) {
      const Batch wv = simd::load(wn + k);
      for (std::int64_t m = 0; m < M; ++m) acc[m] = xsimd::fma(simd::load(x + m * ldx + k), wv, acc[m]);
    }
    if (k < K) {
      const Batch wv = simd::load_partial(wn + k, K - k);
      for (std::int64_t m = 0; m < M; ++m) acc[m] = xsimd::fma(simd::load_partial(x + m * ldx + k, K - k), wv, acc[m]);
    }
    for (std::int64_t m = 0; m < M; ++m) y[m * ldy + n] = simd::reduce_add(acc[m]);
  }
}

// The same with bf16 weights widened in registers; xe/xo hold each row of x split into its
// even and odd elements (row stride `half`), matching simd::load_bf16_pairs.
inline void dot_rows(const float* x, std::int64_t ldx, const float* xe, const float* xo, std::int64_t half,
                     const bf16* w, float* y, std::int64_t ldy, std::int64_t M, std::int64_t n0, std::int64_t n1,
                     std::int64_t K) {
  using simd::Batch;
  constexpr std::int64_t W = simd::kWidth;
  for (std::int64_t n = n0; n < n1; ++n) {
    const auto* wn = reinterpret_cast<const std::uint16_t*>(w + n * K);
    Batch acc[kDotRows] = {Batch(0.f), Batch(0.f), Batch(0.f), Batch(0.f)};
    std::int64_t k = 0;
    for (; k + 2 * W <= K; k += 2 * W) {
      Batch we, wo;
      simd::load_bf16_pairs(wn + k, we, wo);
      for (std::int64_t m = 0; m < M; ++m) {
        acc[m] = xsimd::fma(simd::load(xe + m * half + k / 2), we, acc[m]);
        acc[m] = xsimd::fma(simd::load(xo + m * half + k / 2), wo, acc[m]);
      }
    }
    for (std::int64_t m = 0; m < M; ++m) {
      float t = simd::reduce_add(acc[m]);
      for (std::int64_t kk = k; kk < K; ++kk) t += x[m * ldx + kk] * bf16::to_float(wn[kk]);
      y[m * ldy + n] = t;
    }
  }
}

// y = act(x · wᵀ + b) for M <= kDotRows rows: blocks of 64 output columns among the threads.
template <class W>
void linear_dot_rows(const float* x, std::int64_t ldx, const W* w, const float* b, float* y, std::int64_t ldy,
                     std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi) {
  float* split = nullptr;  // bf16: x rows as [even elements | odd elements]
  const std::int64_t half = K / 2;
  if constexpr (std::is_same_v<W, bf16>) {
    split = scratch_floats(ScratchSlot::SplitRows, 2 * M * half);
    for (std::int64_t m = 0; m < M; ++m)
      for (std::int64_t c = 0; c < half; ++c) {
        split[m * half + c] = x[m * ldx + 2 * c];
        split[(M + m) * half + c] = x[m * ldx + 2 * c + 1];
      }
  }
  constexpr std::int64_t block = 64;
  const std::int64_t blocks = (N + block - 1) / block;
#pragma omp parallel for schedule(dynamic) if (blocks > 1 && N * K >= (1 << 18))
  for (std::int64_t blk = 0; blk < blocks; ++blk) {
    const std::int64_t n0 = blk * block, n1 = std::min(N, n0 + block);
    if constexpr (std::is_same_v<W, float>) dot_rows(x, ldx, w, y, ldy, M, n0, n1, K);
    else dot_rows(x, ldx, split, split + M * half, half, w, y, ldy, M, n0, n1, K);
    apply_epilogue(y + n0, ldy, M, n1 - n0, b ? b + n0 : nullptr, epi, /*parallel=*/false);
  }
}

// Below this many rows a GEMM is nearly a matrix-vector product (modulation vectors, time
// embeddings): bound by reading the weights, which Eigen's GEMV would do on one thread.
inline constexpr std::int64_t kFewRows = 64;

// y = act(x · wᵀ + b) by blocks of output columns shared among the threads: each thread
// widens its block of weights (bf16), multiplies it with Eigen on one thread (Eigen does not
// nest inside a parallel region) and applies the epilogue while the block is in cache.
template <class W>
void linear_column_blocks(const float* x, std::int64_t ldx, const W* w, const float* b, float* y, std::int64_t ldy,
                          std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi) {
  const std::int64_t threads = Eigen::nbThreads();
  // Enough blocks to balance the threads, each at least 16 columns and at most 256 wide.
  const std::int64_t width = std::clamp<std::int64_t>((N + 4 * threads - 1) / (4 * threads), 16, 256);
  const std::int64_t blocks = (N + width - 1) / width;
  CMapRow X(x, M, K, Strided(ldx));
#pragma omp parallel if (blocks > 1 && M * N * K >= (1 << 18))
  {
    std::vector<float> widened(std::is_same_v<W, float> ? 0 : static_cast<std::size_t>(width * K));
#pragma omp for schedule(dynamic)
    for (std::int64_t blk = 0; blk < blocks; ++blk) {
      const std::int64_t n0 = blk * width, nb = std::min(width, N - n0);
      const float* wb;
      if constexpr (std::is_same_v<W, float>) {
        wb = w + n0 * K;
      } else {
        widen_bf16(w + n0 * K, widened.data(), nb * K);
        wb = widened.data();
      }
      MapRow Yb(y + n0, M, nb, Strided(ldy));
      Yb.noalias() = X * CMapRow(wb, nb, K, Strided(K)).transpose();
      apply_epilogue(y + n0, ldy, M, nb, b ? b + n0 : nullptr, epi, /*parallel=*/false);
    }
  }
}

// ---- the packed micro-kernel path -------------------------------------------------------

// The AVX-512 tile: 6×64 where a 512-bit FMA issues once per cycle (AMD Zen 4/5: fewer
// broadcasts per FMA pay), 14×32 elsewhere (two FMA pipes: lighter on L2). EPONA_CPU_TILE=
// tall|wide overrides (benchmarks comparing them; both are tested on every CPU).
inline gemm::Tile avx512_tile() {
  static const gemm::Tile tile = [] {
    const char* env = std::getenv("EPONA_CPU_TILE");
    if (env && *env) {
      const std::string_view v(env);
      EPONA_CHECK(v == "tall" || v == "wide", "EPONA_CPU_TILE='", v, "' is not tall (14x32) or wide (6x64)");
      return v == "tall" ? gemm::Tile::Tall : gemm::Tile::Wide;
    }
    return cpu_features().amd ? gemm::Tile::Wide : gemm::Tile::Tall;
  }();
  return tile;
}

// The micro-kernel family for weights W under `isa` and a product N columns wide; null for
// the generic (Eigen) path. bf16 weights take the AMX tiles (the default where the CPU and OS
// offer them), else the BF16 dot-product kernels, else are widened to float32 while packing
// (no rounding of the activations then); float32 weights take the AVX-512 kernels under both.
// Products narrower than the wide tile take the tall one (no half-empty tiles).
template <class W>
const gemm::KernelFamily* kernel_family(Isa isa, std::int64_t N) {
#if defined(EPONA_GEMM_X86)
  const gemm::Tile tile = N <= 32 ? gemm::Tile::Tall : avx512_tile();
  switch (isa) {
    case Isa::Amx:
      if (std::is_same_v<W, bf16>) return &gemm::amx_bf16();
      [[fallthrough]];
    case Isa::Avx512Bf16:
      return std::is_same_v<W, bf16> ? &gemm::avx512_bf16(tile) : &gemm::avx512_f32(tile);
    case Isa::Avx512: return &gemm::avx512_f32(tile);
    case Isa::Avx2: return &gemm::avx2_f32();
    case Isa::Generic: break;
  }
#endif
  return nullptr;
}

// Packs rows of the activations x (M×K, row stride ldx): float32 steps, or bf16 pairs.
struct PackActivations {
  const gemm::KernelFamily& f;
  const float* x;
  std::int64_t ldx, K;
  void operator()(std::int64_t m0, std::int64_t rows, std::int64_t s0, std::int64_t steps, gemm::Word* dst) const {
    const float* rows_x = x + m0 * ldx;
    if (f.a_rows_major) return gemm::pack_bf16_pairs_rows(rows_x, ldx, rows, f.mr, K, s0, steps, dst, f.avx512_packing);
#if defined(EPONA_GEMM_X86)
    if (f.k_per_step == 2) return gemm::pack_bf16_pairs_rounded(rows_x, ldx, rows, f.mr, K, s0, steps, dst);
    if (f.avx512_packing) return gemm::pack_f32_avx512(rows_x, ldx, rows, f.mr, s0, steps, dst);
#endif
    gemm::pack_transposed(rows_x, ldx, rows, f.mr, s0, steps, dst, gemm::FloatStep{});
  }
};

// Packs rows of the weights w (N×K): float32 steps (bf16 widened), or bf16 pairs as stored;
// panel by panel.
template <class W>
struct PackWeights {
  const gemm::KernelFamily& f;
  const W* w;
  std::int64_t K;
  void operator()(std::int64_t n0, std::int64_t cols, std::int64_t s0, std::int64_t steps, gemm::Word* dst) const {
    // Steps past K (a kernel taking K in whole tiles) are zero.
    const std::int64_t valid = std::clamp<std::int64_t>((K + f.k_per_step - 1) / f.k_per_step - s0, 0, steps);
    for (std::int64_t j = 0; j < cols; j += f.nr) {
      gemm::Word* panel = dst + j * steps;
      pack_panel(n0 + j, std::min<std::int64_t>(f.nr, cols - j), s0, valid, panel);
      std::fill(panel + valid * f.nr, panel + steps * f.nr, gemm::Word{0});
    }
  }
  void pack_panel(std::int64_t n0, std::int64_t cols, std::int64_t s0, std::int64_t steps, gemm::Word* dst) const {
    const W* rows_w = w + n0 * K;
#if defined(EPONA_GEMM_X86)
    if (f.avx512_packing) {
      if constexpr (std::is_same_v<W, float>) return gemm::pack_f32_avx512(rows_w, K, cols, f.nr, s0, steps, dst);
      else if (f.k_per_step == 1) return gemm::pack_bf16_widened_avx512(rows_w, K, cols, f.nr, s0, steps, dst);
      else if (K % 2 == 0) return gemm::pack_bf16_pairs_avx512(rows_w, K, cols, f.nr, s0, steps, dst);
    }
#endif
    if constexpr (std::is_same_v<W, bf16>) {
      if (f.k_per_step == 2) return gemm::pack_transposed(rows_w, K, cols, f.nr, s0, steps, dst, gemm::Bf16PairStep{K});
    }
    gemm::pack_transposed(rows_w, K, cols, f.nr, s0, steps, dst, gemm::FloatStep{});
  }
};

// Bias and activation on a finished tile of y (rows × cols at m0, n0), while it is in L1.
template <class Act>
struct LinearTileEpilogue {
  float* y;
  std::int64_t ldy;
  const float* bias;  // per output column, or null
  Act act;
  void operator()(std::int64_t m0, std::int64_t rows, std::int64_t n0, std::int64_t cols) const {
    for (std::int64_t r = 0; r < rows; ++r) bias_activation_row(y + (m0 + r) * ldy + n0, cols, bias ? bias + n0 : nullptr, act);
  }
};
struct NoEpilogue {
  void operator()(std::int64_t, std::int64_t, std::int64_t, std::int64_t) const {}
};

template <class W>
void linear_packed(const gemm::KernelFamily& f, int threads, const float* x, std::int64_t ldx, const W* w,
                   const float* b, float* y, std::int64_t ldy, std::int64_t M, std::int64_t N, std::int64_t K,
                   Epilogue epi) {
  const std::int64_t steps = ((K + f.k_per_step - 1) / f.k_per_step + f.k_align - 1) / f.k_align * f.k_align;
  const PackActivations pack_a{f, x, ldx, K};
  const PackWeights<W> pack_b{f, w, K};
  if (epi == Epilogue::None && !b) return gemm::run_gemm(f, M, N, steps, threads, pack_a, pack_b, y, ldy, NoEpilogue{});
  with_activation(epi, [&](auto act) {
    gemm::run_gemm(f, M, N, steps, threads, pack_a, pack_b, y, ldy, LinearTileEpilogue<decltype(act)>{y, ldy, b, act});
  });
}
}  // namespace detail

// Pointer form with row strides (x rows ldx apart, y rows ldy apart, so y can be a column
// block of a wider buffer): y[M, N] = act(x[M, K] · w[N, K]ᵀ + bias[N]); bias may be null.
// Up to kDotRows rows: plain dot products over the weights (one pass, bf16 widened in
// registers). More: the packed micro-kernels of active_isa(); on the generic path Eigen's
// threaded GEMM (fp32, >= kFewRows rows) or column blocks shared among the threads.
template <class W>
void linear(Context& ctx, const float* x, std::int64_t ldx, const W* w, const W* bias, float* y, std::int64_t ldy,
            std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi = Epilogue::None) {
  static_assert(std::is_same_v<W, float> || std::is_same_v<W, bf16>, "linear: weights are float or bf16");
  EPONA_CHECK(M >= 0 && N >= 0 && K >= 0, "linear: negative extent (M ", M, ", N ", N, ", K ", K, ")");
  EPONA_CHECK(ldx >= K && ldy >= N, "linear: row strides ldx ", ldx, ", ldy ", ldy, " smaller than K ", K, ", N ", N);
  if (M == 0 || N == 0) return;
  const float* b = nullptr;
  if constexpr (std::is_same_v<W, float>) {
    b = bias;
  } else if (bias) {  // bf16 bias, widened once per call into this thread's scratch
    float* widened = detail::scratch_floats(detail::ScratchSlot::Bias, N);
    detail::widen_bf16(bias, widened, N);
    b = widened;
  }
  if (M <= detail::kDotRows) return detail::linear_dot_rows(x, ldx, w, b, y, ldy, M, N, K, epi);
  if (const gemm::KernelFamily* f = detail::kernel_family<W>(active_isa(), N))
    return detail::linear_packed(*f, ctx.threads(), x, ldx, w, b, y, ldy, M, N, K, epi);
  // Generic path. Large fp32 GEMM: Eigen's own multi-threaded GEMM, then one parallel epilogue.
  if constexpr (std::is_same_v<W, float>) {
    if (M >= detail::kFewRows) {
      detail::CMapRow X(x, M, K, detail::Strided(ldx));
      detail::MapRow Y(y, M, N, detail::Strided(ldy));
      Y.noalias() = X * detail::CMapRow(w, N, K, detail::Strided(K)).transpose();
      detail::apply_epilogue(y, ldy, M, N, b, epi);
      return;
    }
  }
  detail::linear_column_blocks(x, ldx, w, b, y, ldy, M, N, K, epi);
}

// x: (..., K) float32; w: (N, K) float or bf16; bias: (N) or empty; y: (..., N) preallocated.
template <class W>
void linear(Context& ctx, const HostTensor<float>& x, const HostTensor<W>& w, const HostTensor<W>& bias,
            HostTensor<float>& y, Epilogue epi = Epilogue::None) {
  EPONA_CHECK(w.dim() == 2, "linear: weight must be 2-d, got ", shape_str(w.shape()));
  const std::int64_t N = w.size(0), K = w.size(1);
  EPONA_CHECK(K > 0, "linear: weight ", shape_str(w.shape()), " has no input features");
  EPONA_CHECK(x.dim() >= 1 && x.size(-1) == K, "linear: input ", shape_str(x.shape()), " does not end in K=", K);
  const std::int64_t M = x.numel() / K;
  EPONA_CHECK(y.numel() == M * N && y.size(-1) == N, "linear: output ", shape_str(y.shape()), " is not (", M,
              ", ", N, ")");
  EPONA_CHECK(bias.empty() || bias.numel() == N, "linear: bias ", shape_str(bias.shape()), " is not (", N, ")");
  linear<W>(ctx, x.data(), K, w.data(), bias.empty() ? nullptr : bias.data(), y.data(), N, M, N, K, epi);
}

}  // namespace epona::cpu
