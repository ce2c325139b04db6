// epona/cuda/gemm/gemm.cuh — Linear layers on the GPU: y = act(x · Wᵀ + b) with PyTorch's weight
// layout W (out, in), through cuBLASLt. Bias and the tanh GELU run in cuBLASLt's epilogue;
// the erf GELU and SiLU (which cuBLASLt lacks) run as one extra element-wise pass. float32
// uses true float32 arithmetic (CUBLAS_COMPUTE_32F, no TF32); bf16 accumulates in float32.
// New problems of many rows (EPONA_CUDA_GEMM_TUNE: all or none) time a few of cuBLASLt's candidates;
// products with a few outputs per row or a tiny K run in our own kernels (small_linear.cuh).
// The plan, launch and epilogue steps (gemm_common.cuh) are shared with the strided-batched form
// (gemm_batched.cuh).
#pragma once

#include <cstdint>

#include "epona/core/kernel_options.hpp"
#include "epona/cuda/gemm/gemm_common.cuh"

namespace epona::cuda {

// y[M, N] += x[M, K] · w[N, K]ᵀ into a float32 y (rows ldy apart; x rows ldx apart): a residual
// stream updated by the product itself (cuBLASLt's C = D with beta 1), float32 accumulation and
// no rounding of the product to T on the way (under autocast PyTorch rounds the branch to bf16
// before the float32 add: this is the same sum, rounded once instead of twice). No bias.
// Asynchronous on ctx's stream.
template <class T>
void linear_accumulate(Context& ctx, const T* x, std::int64_t ldx, const T* w, float* y, std::int64_t ldy,
                       std::int64_t M, std::int64_t N, std::int64_t K) {
  static_assert(is_device_float<T>, "linear_accumulate takes float or bf16 operands");
  detail::check_product_extent("linear_accumulate", M, N, K, ldx, ldy);
  if (M == 0) return;
  const detail::LtPlanKey key{detail::dtype_tag<T, float>(), M, N, K, ldx, ldy,
                              static_cast<std::int64_t>(CUBLASLT_EPILOGUE_DEFAULT), detail::pointer_alignment(x),
                              detail::pointer_alignment(w), detail::pointer_alignment(y)};
  const detail::LtPlan& plan =
      detail::plan_for<T, float>(ctx, key, CUBLASLT_EPILOGUE_DEFAULT, GemmBatch{}, x, w, nullptr, y, true);
  detail::run_plan(ctx, plan, x, w, static_cast<const T*>(nullptr), y, 1.0f);
}

// x: (..., K); w: (N, K); y: (..., N) float32, preallocated: y += x · wᵀ.
template <class T>
void linear_accumulate(Context& ctx, const Tensor<T, Cuda>& x, const Tensor<T, Cuda>& w, Tensor<float, Cuda>& y) {
  const std::int64_t M = detail::product_rows("linear_accumulate", x, w, y), N = w.size(0), K = w.size(1);
  linear_accumulate(ctx, x.data(), K, w.data(), y.data(), N, M, N, K);
}

// x: (..., K); w: (N, K); bias: (N) or empty; y: (..., N) preallocated. Same dtype throughout.
template <class T>
void linear(Context& ctx, const Tensor<T, Cuda>& x, const Tensor<T, Cuda>& w, const Tensor<T, Cuda>& bias,
            Tensor<T, Cuda>& y, Epilogue epi = Epilogue::None) {
  const std::int64_t M = detail::product_rows("linear", x, w, y), N = w.size(0), K = w.size(1);
  EPONA_CHECK(bias.empty() || bias.numel() == N, "linear: bias ", shape_str(bias.shape()), " is not (", N, ")");
  linear(ctx, x.data(), K, w.data(), bias.empty() ? nullptr : bias.data(), y.data(), N, M, N, K, epi);
}

}  // namespace epona::cuda

// The strided-batched form (several products in one launch) shares the steps above.
#include "epona/cuda/gemm/gemm_batched.cuh"
