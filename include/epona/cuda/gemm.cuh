// epona/cuda/gemm.cuh — Linear layers on the GPU: y = act(x · Wᵀ + b) with PyTorch's weight
// layout W (out, in), through cuBLASLt. Bias and the tanh GELU run in cuBLASLt's epilogue;
// the erf GELU and SiLU (which cuBLASLt lacks) run as one extra element-wise pass. float32
// uses true float32 arithmetic (CUBLAS_COMPUTE_32F, no TF32); bf16 accumulates in float32.
#pragma once

#include <cstdint>
#include <memory>
#include <type_traits>

#include "epona/cuda/activation.cuh"
#include "epona/cuda/elementwise.cuh"
#include "epona/cuda/memory.hpp"

namespace epona::cuda {

enum class Epilogue { None, GeluErf, GeluTanh, Silu };

namespace detail {

// Largest power of two (at most 256) dividing the address: what cuBLASLt may assume.
inline std::int64_t pointer_alignment(const void* p) {
  const auto a = reinterpret_cast<std::uintptr_t>(p);
  std::int64_t align = 256;
  while (align > 1 && a % static_cast<std::uintptr_t>(align) != 0) align /= 2;
  return align;
}

template <class T> constexpr cudaDataType_t cuda_dtype() {
  return std::is_same_v<T, float> ? CUDA_R_32F : CUDA_R_16BF;
}

template <class V>
void set_desc(cublasLtMatmulDesc_t d, cublasLtMatmulDescAttributes_t attr, const V& value) {
  EPONA_CUBLAS_CHECK(cublasLtMatmulDescSetAttribute(d, attr, &value, sizeof value));
}

// Row-major y (M, N) = x (M, K) · w (N, K)ᵀ is, in cuBLASLt's column-major terms,
// yᵀ (N, M) = op_T(w stored K×N) · (x stored K×M).
template <class T>
std::unique_ptr<LtPlan> make_plan(Context& ctx, const LtPlanKey& key, cublasLtEpilogue_t epilogue) {
  const auto [dt, M, N, K, epi, has_bias, ax, aw, ay] = key;
  (void)dt, (void)epi, (void)has_bias;
  const cudaDataType_t type = cuda_dtype<T>();
  auto plan = std::make_unique<LtPlan>();
  EPONA_CUBLAS_CHECK(cublasLtMatmulDescCreate(&plan->op, CUBLAS_COMPUTE_32F, CUDA_R_32F));
  set_desc(plan->op, CUBLASLT_MATMUL_DESC_TRANSA, CUBLAS_OP_T);
  set_desc(plan->op, CUBLASLT_MATMUL_DESC_TRANSB, CUBLAS_OP_N);
  set_desc(plan->op, CUBLASLT_MATMUL_DESC_EPILOGUE, epilogue);
  if (epilogue == CUBLASLT_EPILOGUE_BIAS || epilogue == CUBLASLT_EPILOGUE_GELU_BIAS)
    set_desc(plan->op, CUBLASLT_MATMUL_DESC_BIAS_DATA_TYPE, type);
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutCreate(&plan->a, type, K, N, K));
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutCreate(&plan->b, type, K, M, K));
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutCreate(&plan->c, type, N, M, N));

  cublasLtMatmulPreference_t pref = nullptr;
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceCreate(&pref));
  std::unique_ptr<cublasLtMatmulPreferenceOpaque_t, decltype(&cublasLtMatmulPreferenceDestroy)> pref_guard(
      pref, &cublasLtMatmulPreferenceDestroy);
  const std::uint64_t ws = ctx.workspace_bytes();
  const auto a32 = [](std::int64_t v) { return static_cast<std::uint32_t>(v); };
  const std::uint32_t align_w = a32(aw), align_x = a32(ax), align_y = a32(ay);
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceSetAttribute(pref, CUBLASLT_MATMUL_PREF_MAX_WORKSPACE_BYTES, &ws, sizeof ws));
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceSetAttribute(pref, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_A_BYTES, &align_w,
                                                          sizeof align_w));
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceSetAttribute(pref, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_B_BYTES, &align_x,
                                                          sizeof align_x));
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceSetAttribute(pref, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_C_BYTES, &align_y,
                                                          sizeof align_y));
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceSetAttribute(pref, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_D_BYTES, &align_y,
                                                          sizeof align_y));
  cublasLtMatmulHeuristicResult_t result{};
  int found = 0;
  EPONA_CUBLAS_CHECK(cublasLtMatmulAlgoGetHeuristic(ctx.lt(), plan->op, plan->a, plan->b, plan->c, plan->c, pref, 1,
                                                    &result, &found));
  EPONA_CHECK(found > 0, "linear: cuBLASLt has no algorithm for M=", M, " N=", N, " K=", K, " (",
              std::is_same_v<T, float> ? "float32" : "bf16", ", alignments x ", ax, " w ", aw, " y ", ay, " bytes)");
  plan->algo = result.algo;
  return plan;
}

}  // namespace detail

// Dense row-major y (M, N) = act(x (M, K) · w (N, K)ᵀ + bias (N)); bias may be null.
// Asynchronous on ctx's stream.
template <class T>
void linear(Context& ctx, const T* x, const T* w, const T* bias, T* y, std::int64_t M, std::int64_t N, std::int64_t K,
            Epilogue epi = Epilogue::None) {
  static_assert(is_device_float<T>, "linear takes float or bf16");
  EPONA_CHECK(M >= 0 && N > 0 && K > 0, "linear: bad extent M=", M, " N=", N, " K=", K);
  if (M == 0) return;
  // cuBLASLt's bias epilogue needs a 16-byte aligned bias; otherwise the bias is added apart.
  const bool fused_bias = bias && detail::pointer_alignment(bias) >= 16;
  cublasLtEpilogue_t lt_epi = CUBLASLT_EPILOGUE_DEFAULT;
  if (epi == Epilogue::GeluTanh && (fused_bias || !bias))
    lt_epi = fused_bias ? CUBLASLT_EPILOGUE_GELU_BIAS : CUBLASLT_EPILOGUE_GELU;  // cuBLASLt's GELU is the tanh form
  else if (fused_bias)
    lt_epi = CUBLASLT_EPILOGUE_BIAS;

  const detail::LtPlanKey key{std::is_same_v<T, float> ? 0 : 1, M, N, K, static_cast<std::int64_t>(lt_epi),
                              fused_bias ? 1 : 0, detail::pointer_alignment(x), detail::pointer_alignment(w),
                              detail::pointer_alignment(y)};
  auto& slot = ctx.gemm_plans()[key];
  if (!slot) slot = detail::make_plan<T>(ctx, key, lt_epi);
  if (fused_bias) detail::set_desc(slot->op, CUBLASLT_MATMUL_DESC_BIAS_POINTER, static_cast<const void*>(bias));
  const float alpha = 1.0f, beta = 0.0f;
  EPONA_CUBLAS_CHECK(cublasLtMatmul(ctx.lt(), slot->op, &alpha, w, slot->a, x, slot->b, &beta, y, slot->c, y, slot->c,
                                    &slot->algo, ctx.workspace(), ctx.workspace_bytes(), ctx.stream()));

  const std::int64_t n = M * N;
  if (bias && !fused_bias) add_row_broadcast(ctx, y, bias, M, N);
  switch (epi) {
    case Epilogue::None: break;
    case Epilogue::GeluTanh:
      if (lt_epi == CUBLASLT_EPILOGUE_DEFAULT) gelu_tanh(ctx, y, n);
      break;
    case Epilogue::GeluErf: gelu_erf(ctx, y, n); break;
    case Epilogue::Silu: silu(ctx, y, n); break;
  }
}

// x: (..., K); w: (N, K); bias: (N) or empty; y: (..., N) preallocated. Same dtype throughout.
template <class T>
void linear(Context& ctx, const Tensor<T, Cuda>& x, const Tensor<T, Cuda>& w, const Tensor<T, Cuda>& bias,
            Tensor<T, Cuda>& y, Epilogue epi = Epilogue::None) {
  EPONA_CHECK(w.dim() == 2, "linear: weight must be 2-d, got ", shape_str(w.shape()));
  const std::int64_t N = w.size(0), K = w.size(1);
  EPONA_CHECK(x.dim() >= 1 && x.size(-1) == K, "linear: input ", shape_str(x.shape()), " does not end in K=", K);
  const std::int64_t M = x.numel() / K;
  EPONA_CHECK(y.numel() == M * N && y.size(-1) == N, "linear: output ", shape_str(y.shape()), " is not (", M, ", ",
              N, ")");
  EPONA_CHECK(bias.empty() || bias.numel() == N, "linear: bias ", shape_str(bias.shape()), " is not (", N, ")");
  linear(ctx, x.data(), w.data(), bias.empty() ? nullptr : bias.data(), y.data(), M, N, K, epi);
}

}  // namespace epona::cuda
