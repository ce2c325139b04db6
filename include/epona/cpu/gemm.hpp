// epona/cpu/gemm.hpp — Linear layers on the CPU: y = act(x · Wᵀ + b) with PyTorch's weight
// layout W (out, in). float32 weights go straight to Eigen's multi-threaded GEMM; bfloat16
// weights are widened to float32 in blocks (fp32 accumulation).
#pragma once

#include <Eigen/Core>
#include <cstring>
#include <vector>

#include "epona/cpu/activation.hpp"
#include "epona/cpu/context.hpp"

namespace epona::cpu {

enum class Epilogue { None, GeluErf, GeluTanh, Silu };

namespace detail {
using RowMat = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using MapRow = Eigen::Map<RowMat>;
using CMapRow = Eigen::Map<const RowMat>;

inline void apply_epilogue(Context& ctx, float* y, std::int64_t n, Epilogue e) {
  switch (e) {
    case Epilogue::None: break;
    case Epilogue::GeluErf: gelu_erf(ctx, y, n); break;
    case Epilogue::GeluTanh: gelu_tanh(ctx, y, n); break;
    case Epilogue::Silu: silu(ctx, y, n); break;
  }
}
}  // namespace detail

// x: (..., K) float32; w: (N, K) float or bf16; bias: (N) or empty; y: (..., N) preallocated.
template <class W>
void linear(Context& ctx, const HostTensor<float>& x, const HostTensor<W>& w, const HostTensor<W>& bias,
            HostTensor<float>& y, Epilogue epi = Epilogue::None) {
  EPONA_CHECK(w.dim() == 2, "linear: weight must be 2-d, got ", shape_str(w.shape()));
  const std::int64_t N = w.size(0), K = w.size(1);
  EPONA_CHECK(x.dim() >= 1 && x.size(-1) == K, "linear: input ", shape_str(x.shape()), " does not end in K=", K);
  const std::int64_t M = x.numel() / K;
  EPONA_CHECK(y.numel() == M * N && y.size(-1) == N, "linear: output ", shape_str(y.shape()), " is not (", M,
              ", ", N, ")");
  EPONA_CHECK(bias.empty() || bias.numel() == N, "linear: bias ", shape_str(bias.shape()), " is not (", N, ")");
  detail::CMapRow X(x.data(), M, K);
  detail::MapRow Y(y.data(), M, N);
  if constexpr (std::is_same_v<W, float>) {
    detail::CMapRow Wm(w.data(), N, K);
    Y.noalias() = X * Wm.transpose();
  } else {
    // Widen bf16 weights block by block (keeps memory bounded for large layers).
    constexpr std::int64_t block = 256;
    std::vector<float> wf(static_cast<std::size_t>(block * K));
    for (std::int64_t n0 = 0; n0 < N; n0 += block) {
      const std::int64_t nb = std::min(block, N - n0);
      for (std::int64_t i = 0; i < nb * K; ++i) wf[i] = float(w.data()[n0 * K + i]);
      detail::CMapRow Wm(wf.data(), nb, K);
      Y.middleCols(n0, nb).noalias() = X * Wm.transpose();
    }
  }
  if (!bias.empty()) {
    float* yp = y.data();
#pragma omp parallel for
    for (std::int64_t m = 0; m < M; ++m)
      for (std::int64_t n = 0; n < N; ++n) yp[m * N + n] += float(bias.data()[n]);
  }
  detail::apply_epilogue(ctx, y.data(), y.numel(), epi);
}

}  // namespace epona::cpu
