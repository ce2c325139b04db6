// epona/cuda/gemm/gemm_common.cuh — what gemm.cuh and the strided-batched form (gemm_batched.cuh)
// share: cuBLASLt plans (made, tuned and cached per problem), their launch, the epilogues
// cuBLASLt lacks, and the pointer form of linear. Its own header so that the two include it
// and not each other.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <memory>
#include <type_traits>
#include <vector>

#include "epona/core/env.hpp"
#include "epona/cuda/pointwise/activation.cuh"
#include "epona/core/kernel_options.hpp"
#include "epona/cuda/runtime/memory.hpp"
#include "epona/cuda/gemm/gemm_few_rows.cuh"
#include "epona/cuda/gemm/gemm_wgmma.cuh"
#include "epona/cuda/gemm/small_linear.cuh"

namespace epona::cuda {

using epona::Epilogue;

// A strided-batched product: `count` items, each operand's items `x`, `w`, `bias`, `y` elements
// apart (any sign; 0 repeats the operand). count 1 is the plain product.
struct GemmBatch {
  std::int32_t count = 1;
  std::int64_t x = 0, w = 0, bias = 0, y = 0;
};

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

// Tuning: a new plan times cuBLASLt's first few heuristic candidates on its first call outside
// a graph capture and keeps the fastest. Candidates that add split-K partial sums in the output
// type (bf16: extra roundings) are not considered; products that add to their output are timed
// on a scratch buffer. EPONA_CUDA_GEMM_TUNE=1 times every new plan, 0 none; unset, the
// products of at least kTuneRowsMin rows (the MST's 5150-row ones: the heuristic's first choice
// for its c_fc takes 223 us, the fastest candidate 215 us; the MST 0.2 ms faster, H200,
// docs/gpu-log.md "Session 17"). The DiTs' small-M products stay untimed: timing them did not
// pay inside their sampler graphs (same run, bf16: TrajDiT-100 13.41 -> 13.29 ms, VisDiT-100
// 280.1 -> 283.6 ms). Which candidate wins can differ between processes; every candidate sums
// in float32 and rounds once, so the outputs agree to the rounding of the output type.
// The choice is ctx.policy().gemm_tuning (KernelPolicy, runtime/kernel_policy.hpp).
inline constexpr std::int64_t kTuneRowsMin = 4096;
// Whether a new plan of a product of `rows` rows is timed.
inline bool gemm_tuning(const Context& ctx, std::int64_t rows) {
  const GemmTuning t = ctx.policy().gemm_tuning;
  return t == GemmTuning::All || (t == GemmTuning::Large && rows >= kTuneRowsMin);
}
constexpr int kTuneCandidates = 8, kTuneRuns = 10;
// Untuned plans (tuning off, or made during a capture where nothing can be timed) are kept
// under their key with this bit set in the epilogue field, so they never stand in for a tuned
// one: a later call outside a capture with tuning on makes and tunes the plan of the plain key.
constexpr std::int64_t kUntunedPlan = std::int64_t{1} << 40;

template <class V>
void set_layout(cublasLtMatrixLayout_t l, cublasLtMatrixLayoutAttribute_t attr, const V& value) {
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutSetAttribute(l, attr, &value, sizeof value));
}

// Writes the batch count and strides into a plan's descriptors. A cached batched plan is keyed
// by the strides' alignments and signs, not their values (each layer's weights lie at another
// distance), so every call sets its own strides, as it sets its bias pointer.
inline void apply_batch(LtPlan& plan, const GemmBatch& batch) {
  const auto strided = [&](cublasLtMatrixLayout_t l, std::int64_t stride) {
    set_layout(l, CUBLASLT_MATRIX_LAYOUT_BATCH_COUNT, batch.count);
    set_layout(l, CUBLASLT_MATRIX_LAYOUT_STRIDED_BATCH_OFFSET, stride);
  };
  strided(plan.a, batch.w);
  strided(plan.b, batch.x);
  strided(plan.c, batch.y);
  set_desc(plan.op, CUBLASLT_MATMUL_DESC_BIAS_BATCH_STRIDE, batch.bias);
}

// Row-major y (M, N) = x (M, K) · w (N, K)ᵀ is, in cuBLASLt's column-major terms,
// yᵀ (N, M) = op_T(w stored K×N) · (x stored K×M). Returns null when cuBLASLt has no
// algorithm for this epilogue. `candidates` (if given) receives the heuristic's first few
// algorithms that reduce split-K partial sums in float32 or not at all (the first always).
template <class T, class TY = T>
std::unique_ptr<LtPlan> try_plan(Context& ctx, const LtPlanKey& key, cublasLtEpilogue_t epilogue, const GemmBatch& batch,
                                 std::vector<cublasLtMatmulAlgo_t>* candidates = nullptr) {
  const auto [dt, M, N, K, ldx, ldy, wanted, ax, aw, ay] = key;
  (void)dt, (void)wanted;
  const cudaDataType_t type = cuda_dtype<T>(), out_type = cuda_dtype<TY>();
  auto plan = std::make_unique<LtPlan>();
  plan->epilogue = epilogue;
  EPONA_CUBLAS_CHECK(cublasLtMatmulDescCreate(&plan->op, CUBLAS_COMPUTE_32F, CUDA_R_32F));
  set_desc(plan->op, CUBLASLT_MATMUL_DESC_TRANSA, CUBLAS_OP_T);
  set_desc(plan->op, CUBLASLT_MATMUL_DESC_TRANSB, CUBLAS_OP_N);
  set_desc(plan->op, CUBLASLT_MATMUL_DESC_EPILOGUE, epilogue);
  if (plan->fuses_bias()) set_desc(plan->op, CUBLASLT_MATMUL_DESC_BIAS_DATA_TYPE, out_type);
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutCreate(&plan->a, type, K, N, K));
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutCreate(&plan->b, type, K, M, ldx));
  EPONA_CUBLAS_CHECK(cublasLtMatrixLayoutCreate(&plan->c, out_type, N, M, ldy));
  if (batch.count > 1) apply_batch(*plan, batch);

  cublasLtMatmulPreference_t pref = nullptr;
  EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceCreate(&pref));
  std::unique_ptr<cublasLtMatmulPreferenceOpaque_t, decltype(&cublasLtMatmulPreferenceDestroy)> pref_guard(
      pref, &cublasLtMatmulPreferenceDestroy);
  const auto set_pref = [pref](cublasLtMatmulPreferenceAttributes_t attr, auto value) {
    EPONA_CUBLAS_CHECK(cublasLtMatmulPreferenceSetAttribute(pref, attr, &value, sizeof value));
  };
  set_pref(CUBLASLT_MATMUL_PREF_MAX_WORKSPACE_BYTES, static_cast<std::uint64_t>(ctx.workspace_bytes()));
  set_pref(CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_A_BYTES, static_cast<std::uint32_t>(aw));
  set_pref(CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_B_BYTES, static_cast<std::uint32_t>(ax));
  set_pref(CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_C_BYTES, static_cast<std::uint32_t>(ay));
  set_pref(CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_D_BYTES, static_cast<std::uint32_t>(ay));
  cublasLtMatmulHeuristicResult_t results[kTuneCandidates]{};
  int found = 0;
  const cublasStatus_t status = cublasLtMatmulAlgoGetHeuristic(
      ctx.lt(), plan->op, plan->a, plan->b, plan->c, plan->c, pref, candidates ? kTuneCandidates : 1, results, &found);
  if (status == CUBLAS_STATUS_NOT_SUPPORTED || found == 0) return nullptr;
  EPONA_CUBLAS_CHECK(status);
  plan->algo = results[0].algo;
  if (candidates)
    for (int i = 0; i < found; ++i) {
      std::uint32_t scheme = CUBLASLT_REDUCTION_SCHEME_NONE;
      std::size_t written = 0;
      EPONA_CUBLAS_CHECK(cublasLtMatmulAlgoConfigGetAttribute(&results[i].algo, CUBLASLT_ALGO_CONFIG_REDUCTION_SCHEME,
                                                              &scheme, sizeof scheme, &written));
      if (i == 0 || scheme == CUBLASLT_REDUCTION_SCHEME_NONE || scheme == CUBLASLT_REDUCTION_SCHEME_COMPUTE_TYPE)
        candidates->push_back(results[i].algo);
    }
  return plan;
}

// Times each candidate on the call's own operands (in stream order before the call itself, so
// y is simply overwritten) and keeps the fastest in the plan. A product that adds to its output
// (beta 1: `y_elems` elements from y) is timed on a zeroed scratch buffer of that size instead.
template <class T, class TY>
void tune_plan(Context& ctx, LtPlan& plan, const std::vector<cublasLtMatmulAlgo_t>& candidates, const T* x,
               const T* w, const T* bias, TY* y, float beta, std::int64_t y_elems) {
  if (candidates.size() < 2) return;
  if (plan.fuses_bias()) set_desc(plan.op, CUBLASLT_MATMUL_DESC_BIAS_POINTER, static_cast<const void*>(bias));
  Tensor<TY, Cuda> scratch;
  if (beta != 0.0f) {
    scratch = Tensor<TY, Cuda>({y_elems});
    fill_bytes(ctx, scratch, 0);
    y = scratch.data();
  }
  cudaEvent_t events[2] = {nullptr, nullptr};
  for (auto& e : events) EPONA_CUDA_CHECK(cudaEventCreate(&e));
  const float alpha = 1.0f;
  float best = 0;
  cublasLtMatmulAlgo_t chosen = plan.algo;
  for (const auto& algo : candidates) {
    const auto run = [&] {
      return cublasLtMatmul(ctx.lt(), plan.op, &alpha, w, plan.a, x, plan.b, &beta, y, plan.c, y, plan.c, &algo,
                            ctx.workspace(), ctx.workspace_bytes(), ctx.stream());
    };
    if (run() != CUBLAS_STATUS_SUCCESS) continue;  // warm-up; an algorithm that refuses is skipped
    EPONA_CUDA_CHECK(cudaEventRecord(events[0], ctx.stream()));
    for (int r = 0; r < kTuneRuns; ++r) EPONA_CUBLAS_CHECK(run());
    EPONA_CUDA_CHECK(cudaEventRecord(events[1], ctx.stream()));
    EPONA_CUDA_CHECK(cudaEventSynchronize(events[1]));
    float ms = 0;
    EPONA_CUDA_CHECK(cudaEventElapsedTime(&ms, events[0], events[1]));
    if (best == 0 || ms < best) best = ms, chosen = algo;
  }
  for (auto e : events) EPONA_CUDA_CHECK(cudaEventDestroy(e));
  plan.algo = chosen;
}

// The wanted fused epilogue if cuBLASLt has it for this problem, else a plain product (the
// caller then applies bias and activation itself).
template <class T, class TY = T>
std::unique_ptr<LtPlan> make_plan(Context& ctx, const LtPlanKey& key, cublasLtEpilogue_t wanted, const GemmBatch& batch,
                                  std::vector<cublasLtMatmulAlgo_t>* candidates = nullptr) {
  auto plan = try_plan<T, TY>(ctx, key, wanted, batch, candidates);
  if (!plan && wanted != CUBLASLT_EPILOGUE_DEFAULT)
    plan = try_plan<T, TY>(ctx, key, CUBLASLT_EPILOGUE_DEFAULT, batch, candidates);
  EPONA_CHECK(plan != nullptr, "linear: cuBLASLt has no algorithm for M=", key[1], " N=", key[2], " K=", key[3],
              " ldx=", key[4], " ldy=", key[5], " batch ", batch.count, " (", std::is_same_v<T, float> ? "float32" : "bf16",
              std::is_same_v<T, TY> ? "" : " into float32", ", alignments x ", key[7], " w ", key[8], " y ", key[9], " bytes)");
  return plan;
}

// y[r, c] = op(y[r, c] + bias[c]) on rows ldy apart; bias may be null. A bias that was not
// fused rounds the sum to T first, as cuBLASLt's output (and PyTorch's Linear) would be.
template <class T, class Op>
struct BiasActivationEach {
  T* y;
  std::int64_t ldy;
  const T* bias;
  Op op;
  __device__ void pack(std::int64_t r, std::int64_t c) const {
    float v[kPack], b[kPack];
    load8(y + r * ldy + c, v);
    if (bias) load8(bias + c, b);
#pragma unroll
    for (int i = 0; i < kPack; ++i) v[i] = op(bias ? round_to<T>(v[i] + b[i]) : v[i]);
    store8(y + r * ldy + c, v);
  }
  __device__ void one(std::int64_t r, std::int64_t c) const {
    float v = to_f32(y[r * ldy + c]);
    if (bias) v = round_to<T>(v + to_f32(bias[c]));
    y[r * ldy + c] = from_f32<T>(op(v));
  }
};

template <class T, class Op>
void bias_activation(Context& ctx, T* y, std::int64_t ldy, std::int64_t rows, std::int64_t n, const T* bias, Op op) {
  const bool packed = packable(y, n, ldy) && packable(bias, n, 0);
  for_each(ctx, rows, n, packed, BiasActivationEach<T, Op>{y, ldy, bias, op});
}

// The activation pass after cuBLASLt: contiguous bf16 with no bias left goes through the
// activation's lookup table (activation.cuh: same bits, memory speed), the rest one pass here.
template <class T, class Op>
void activation_epilogue(Context& ctx, T* y, std::int64_t ldy, std::int64_t rows, std::int64_t n, const T* bias, Op op) {
  if constexpr (std::is_same_v<T, bf16>)
    if (!bias && ldy == n) return map_bf16(ctx, y, y, rows * n, op);
  bias_activation(ctx, y, ldy, rows, n, bias, op);
}

// The cuBLASLt epilogue to ask for: cuBLASLt's GELU is the tanh form; its bias epilogue needs
// a 16-byte aligned bias (`bias_alignment`: of every batch item's), otherwise the bias is added apart.
inline cublasLtEpilogue_t wanted_epilogue(Epilogue epi, bool has_bias, std::int64_t bias_alignment) {
  const bool bias_fusable = has_bias && bias_alignment >= 16;
  if (epi == Epilogue::GeluTanh && (bias_fusable || !has_bias))
    return has_bias ? CUBLASLT_EPILOGUE_GELU_BIAS : CUBLASLT_EPILOGUE_GELU;
  return bias_fusable ? CUBLASLT_EPILOGUE_BIAS : CUBLASLT_EPILOGUE_DEFAULT;
}

// The cached plan of `key` (made, and with tuning on timed on this call's operands, when new).
// `accumulates`: the call adds to y (beta 1), so the timing runs go to a scratch buffer.
template <class T, class TY = T>
LtPlan& plan_for(Context& ctx, const LtPlanKey& key, cublasLtEpilogue_t wanted, const GemmBatch& batch, const T* x,
                 const T* w, const T* bias, TY* y, bool accumulates = false) {
  auto& plans = ctx.gemm_plans();
  const bool tuning = gemm_tuning(ctx, key[1]) && (!accumulates || batch.count == 1);
  if (auto it = plans.find(key); tuning && it != plans.end()) return *it->second;
  if (!tuning || capturing(ctx.stream())) {
    auto untuned = key;
    untuned[6] |= kUntunedPlan;
    auto& p = plans[untuned];
    if (!p) p = make_plan<T, TY>(ctx, untuned, wanted, batch);
    return *p;
  }
  std::vector<cublasLtMatmulAlgo_t> candidates;
  auto p = make_plan<T, TY>(ctx, key, wanted, batch, &candidates);
  const std::int64_t y_elems = (key[1] - 1) * key[5] + key[2];  // (M - 1) ldy + N: one item's extent
  tune_plan(ctx, *p, candidates, x, w, bias, y, accumulates ? 1.0f : 0.0f, y_elems);
  return *(plans[key] = std::move(p));
}

// The product itself (every batch item the plan's layouts name), asynchronous on ctx's stream;
// beta 1 adds it to y.
template <class T, class TY>
void run_plan(Context& ctx, const LtPlan& plan, const T* x, const T* w, const T* bias, TY* y, float beta = 0.0f) {
  if (plan.fuses_bias()) set_desc(plan.op, CUBLASLT_MATMUL_DESC_BIAS_POINTER, static_cast<const void*>(bias));
  const float alpha = 1.0f;
  EPONA_CUBLAS_CHECK(cublasLtMatmul(ctx.lt(), plan.op, &alpha, w, plan.a, x, plan.b, &beta, y, plan.c, y, plan.c,
                                    &plan.algo, ctx.workspace(), ctx.workspace_bytes(), ctx.stream()));
}

// What cuBLASLt did not do for y (M, N) rows ldy apart, in one pass: the bias when unfused,
// then the activation (always for the erf GELU and SiLU, which cuBLASLt lacks).
template <class T>
void finish_epilogue(Context& ctx, const LtPlan& plan, Epilogue epi, T* y, std::int64_t ldy, std::int64_t M,
                     std::int64_t N, const T* bias) {
  const T* rest_bias = plan.fuses_bias() ? nullptr : bias;
  switch (epi) {
    case Epilogue::None:
      if (rest_bias) bias_activation(ctx, y, ldy, M, N, rest_bias, Identity{});
      break;
    case Epilogue::GeluTanh:
      if (!plan.fuses_gelu()) activation_epilogue(ctx, y, ldy, M, N, rest_bias, GeluTanhOp{});
      break;
    case Epilogue::GeluErf: activation_epilogue(ctx, y, ldy, M, N, rest_bias, GeluErfOp{}); break;
    case Epilogue::Silu: activation_epilogue(ctx, y, ldy, M, N, rest_bias, SiluOp{}); break;
  }
}

// The extent and row-stride checks every product's pointer form makes (`what` names it).
inline void check_product_extent(const char* what, std::int64_t M, std::int64_t N, std::int64_t K, std::int64_t ldx,
                                 std::int64_t ldy) {
  EPONA_CHECK(M >= 0 && N > 0 && K > 0, what, ": bad extent (M ", M, ", N ", N, ", K ", K, ")");
  EPONA_CHECK(ldx >= K && ldy >= N, what, ": row strides ldx ", ldx, ", ldy ", ldy, " smaller than K ", K, ", N ", N);
}

// M of a Tensor-form product x (..., K) · w (N, K)ᵀ -> y (..., N), the shapes checked.
template <class TX, class TW, class TY>
std::int64_t product_rows(const char* what, const Tensor<TX, Cuda>& x, const Tensor<TW, Cuda>& w,
                          const Tensor<TY, Cuda>& y) {
  EPONA_CHECK(w.dim() == 2, what, ": weight must be 2-d, got ", shape_str(w.shape()));
  const std::int64_t N = w.size(0), K = w.size(1);
  EPONA_CHECK(x.dim() >= 1 && x.size(-1) == K, what, ": input ", shape_str(x.shape()), " does not end in K=", K);
  const std::int64_t M = x.numel() / K;
  EPONA_CHECK(y.numel() == M * N && y.size(-1) == N, what, ": output ", shape_str(y.shape()), " is not (", M, ", ", N,
              ")");
  return M;
}

// The operand and output types of a plan: float32, bf16, or bf16 operands into a float32 output.
template <class T, class TY = T> constexpr std::int64_t dtype_tag() {
  return std::is_same_v<T, float> ? 0 : std::is_same_v<TY, float> ? 2 : 1;
}

}  // namespace detail

// Whether models add residual branches inside the product (linear_accumulate) rather than in
// the norm pass after it: ctx.policy().residual_gemm (EPONA_CUDA_RESIDUAL_GEMM=0: in the norm
// pass after a product that writes its own output, for side-by-side runs). Plans made before a
// change of ctx.policy().gemm_tuning keep their algorithm.
inline bool residual_gemm_enabled(const Context& ctx) { return ctx.policy().residual_gemm; }

// Pointer form with row strides (x rows ldx apart, y rows ldy apart, so y can be a column
// block of a wider buffer): y[M, N] = act(x[M, K] · w[N, K]ᵀ + bias[N]); bias may be null.
// Asynchronous on ctx's stream.
template <class T>
void linear(Context& ctx, const T* x, std::int64_t ldx, const T* w, const T* bias, T* y, std::int64_t ldy,
            std::int64_t M, std::int64_t N, std::int64_t K, Epilogue epi = Epilogue::None) {
  static_assert(is_device_float<T>, "linear takes float or bf16");
  detail::check_product_extent("linear", M, N, K, ldx, ldy);
  if (M == 0) return;
  // Shapes cuBLASLt's tiles fit badly (a few outputs per row, a tiny K): our own kernels, which
  // say which epilogues they take (small_linear.cuh).
  // ctx.policy().small_gemm off (EPONA_CUDA_SMALL_GEMM=0) sends every product to cuBLASLt.
  if (ctx.policy().small_gemm && detail::small_linear(ctx, x, ldx, w, bias, y, ldy, M, N, K, epi)) return;
  if constexpr (std::is_same_v<T, bf16>) {
    if (epi == Epilogue::GeluErf && detail::own_gemm_wins(ctx, M, K) &&  // the erf GELU fused (cuBLASLt lacks it)
        detail::own_gemm(ctx, x, ldx, w, bias, y, ldy, M, N, K, detail::GeluErfOp{}))
      return;
    if (detail::few_rows_wins(ctx, M, K) &&  // a programmatic launch in the DiTs' condition chains
        detail::few_rows_gemm(ctx, x, ldx, w, bias, y, ldy, M, N, K, epi))
      return;
  }
  const cublasLtEpilogue_t wanted = detail::wanted_epilogue(epi, bias != nullptr, detail::pointer_alignment(bias));
  const detail::LtPlanKey key{detail::dtype_tag<T>(), M, N, K, ldx, ldy, static_cast<std::int64_t>(wanted),
                              detail::pointer_alignment(x), detail::pointer_alignment(w),
                              detail::pointer_alignment(y)};
  const detail::LtPlan& plan = detail::plan_for(ctx, key, wanted, GemmBatch{}, x, w, bias, y);
  detail::run_plan(ctx, plan, x, w, bias, y);
  detail::finish_epilogue(ctx, plan, epi, y, ldy, M, N, bias);
}

}  // namespace epona::cuda
