// epona/cpu/gemm.hpp — Linear layers on the CPU: y = act(x · Wᵀ + b) with PyTorch's weight
// layout W (out, in). float32 weights go straight to Eigen's multi-threaded GEMM; bfloat16
// weights are widened to float32 in blocks (fp32 accumulation). Bias and activation are
// fused into one vectorised pass over the output.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#include "epona/cpu/context.hpp"  // first: includes Eigen with GCC 12's false positives silenced
#include "epona/cpu/activation.hpp"
#include "epona/cpu/simd.hpp"

namespace epona::cpu {

enum class Epilogue { None, GeluErf, GeluTanh, Silu };

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

struct Identity {
  simd::Batch operator()(const simd::Batch& x) const { return x; }
};

// y[m, :] = act(y[m, :] + bias) over rows of width n (row stride ldy); bias may be null.
template <class Act>
inline void bias_activation(float* y, std::int64_t ldy, std::int64_t rows, std::int64_t n, const float* bias, Act act) {
  using simd::Batch;
  simd::for_each_row(rows, n, [=](std::int64_t r) {
    float* yr = y + r * ldy;
    if (bias) simd::map(n, yr, [act](const Batch& v, const Batch& b) { return act(v + b); }, yr, bias);
    else simd::map(n, yr, act, yr);
  });
}

inline void apply_epilogue(float* y, std::int64_t ldy, std::int64_t rows, std::int64_t n, const float* bias,
                           Epilogue e) {
  switch (e) {
    case Epilogue::None:
      if (bias) bias_activation(y, ldy, rows, n, bias, Identity{});
      break;
    case Epilogue::GeluErf: bias_activation(y, ldy, rows, n, bias, act::GeluErf{}); break;
    case Epilogue::GeluTanh: bias_activation(y, ldy, rows, n, bias, act::GeluTanh{}); break;
    case Epilogue::Silu: bias_activation(y, ldy, rows, n, bias, act::Silu{}); break;
  }
}

// Kept for callers of the first version: the epilogue alone on a contiguous buffer.
inline void apply_epilogue(Context&, float* y, std::int64_t n, Epilogue e) { apply_epilogue(y, n, 1, n, nullptr, e); }
}  // namespace detail

// Pointer form with row strides (x rows ldx apart, y rows ldy apart, so y can be a column
// block of a wider buffer): y[M, N] = act(x[M, K] · w[N, K]ᵀ + bias[N]); bias may be null.
template <class W>
void linear(Context&, const float* x, std::int64_t ldx, const W* w, const W* bias, float* y, std::int64_t ldy,
            std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi = Epilogue::None) {
  static_assert(std::is_same_v<W, float> || std::is_same_v<W, bf16>, "linear: weights are float or bf16");
  EPONA_CHECK(M >= 0 && N >= 0 && K >= 0, "linear: negative extent (M ", M, ", N ", N, ", K ", K, ")");
  EPONA_CHECK(ldx >= K && ldy >= N, "linear: row strides ldx ", ldx, ", ldy ", ldy, " smaller than K ", K, ", N ", N);
  if (M == 0 || N == 0) return;
  detail::CMapRow X(x, M, K, detail::Strided(ldx));
  detail::MapRow Y(y, M, N, detail::Strided(ldy));
  std::vector<float> bias_f;
  const float* b = nullptr;
  if constexpr (std::is_same_v<W, float>) {
    detail::CMapRow Wm(w, N, K, detail::Strided(K));
    Y.noalias() = X * Wm.transpose();
    b = bias;
  } else {
    // Widen bf16 weights block by block (keeps memory bounded for large layers).
    constexpr std::int64_t block = 256;
    std::vector<float> wf(static_cast<std::size_t>(std::min(block, N) * K));
    for (std::int64_t n0 = 0; n0 < N; n0 += block) {
      const std::int64_t nb = std::min(block, N - n0);
      detail::widen_bf16(w + n0 * K, wf.data(), nb * K);
      detail::CMapRow Wm(wf.data(), nb, K, detail::Strided(K));
      Y.middleCols(n0, nb).noalias() = X * Wm.transpose();
    }
    if (bias) {
      bias_f.resize(static_cast<std::size_t>(N));
      detail::widen_bf16(bias, bias_f.data(), N);
      b = bias_f.data();
    }
  }
  detail::apply_epilogue(y, ldy, M, N, b, epi);
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
