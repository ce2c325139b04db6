// epona/cuda/gemm/gemm_batched.cuh — several Linear products of one shape as one strided-batched
// cuBLASLt product (each item its own x, W, bias, y), and linear_pair: two layers' products
// (a FLUX double block's condition and target streams, which have separate weights) in one
// launch. Same arithmetic per element as cuda::linear (float32 sums, one rounding, same epilogues).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <optional>
#include <vector>

#include "epona/core/env.hpp"
#include "epona/cuda/gemm/gemm_common.cuh"

namespace epona::cuda {

namespace detail {


// p advanced by `elems` elements, computed on the address: batch items may lie in different
// allocations (two layers' weights), where pointer arithmetic would not be defined.
template <class T>
T* advance(T* p, std::int64_t elems) {
  const auto bytes = static_cast<std::intptr_t>(elems * static_cast<std::int64_t>(sizeof(T)));
  return reinterpret_cast<T*>(reinterpret_cast<std::uintptr_t>(p) + static_cast<std::uintptr_t>(bytes));
}

// Elements from a to b, when the byte distance is a whole number of elements.
template <class T>
std::optional<std::int64_t> element_distance(const T* a, const T* b) {
  const auto bytes = static_cast<std::int64_t>(reinterpret_cast<std::intptr_t>(b) - reinterpret_cast<std::intptr_t>(a));
  if (bytes % static_cast<std::int64_t>(sizeof(T)) != 0) return std::nullopt;
  return bytes / static_cast<std::int64_t>(sizeof(T));
}

// The alignment every item's start keeps: the base's and the stride's (item b is base + b·stride).
template <class T>
std::int64_t batch_alignment(const T* base, std::int64_t stride) {
  const auto stride_bytes = static_cast<std::uintptr_t>(std::llabs(stride) * static_cast<std::int64_t>(sizeof(T)));
  return std::min(pointer_alignment(base), pointer_alignment(reinterpret_cast<const void*>(stride_bytes)));
}

// The plan key of a batched product: linear's fields, with the count in the dtype field
// (linear's keys hold 0 or 1 there) and each operand's batch alignment.
template <class T>
LtPlanKey batched_key(std::int64_t M, std::int64_t N, std::int64_t K, std::int64_t ldx, std::int64_t ldy,
                      cublasLtEpilogue_t wanted, const T* x, const T* w, const T* y, const GemmBatch& b) {
  const std::int64_t tag = dtype_tag<T>() | std::int64_t{b.count} << 8;
  return {tag, M, N, K, ldx, ldy, static_cast<std::int64_t>(wanted), batch_alignment(x, b.x), batch_alignment(w, b.w),
          batch_alignment(y, b.y)};
}

// Strides cuBLASLt's batched kernels take: none negative (its bf16 kernels read out of bounds
// with one on the H200; float32 ran) and none of 2^40 bytes or more (a TMA tensor map's limit).
template <class T>
bool cublaslt_strides(const GemmBatch& b) {
  constexpr std::int64_t limit = (std::int64_t{1} << 40) / static_cast<std::int64_t>(sizeof(T));
  for (const std::int64_t s : {b.x, b.w, b.bias, b.y})
    if (s < 0 || s >= limit) return false;
  return true;
}
inline bool no_positive_stride(const GemmBatch& b) { return b.x <= 0 && b.w <= 0 && b.bias <= 0 && b.y <= 0; }

}  // namespace detail

// Whether linear_pair is the double blocks' path (ADL hook of nn::Linear::pair_available):
// ctx.policy().pair_gemm (EPONA_CUDA_PAIR_GEMM=0: one product per stream, side-by-side runs).
inline bool pair_gemm_enabled(const Context& ctx) { return ctx.policy().pair_gemm; }

// y_b[M, N] = act(x_b[M, K] · w_bᵀ + bias_b) for b < batch.count, with x_b = x + b·batch.x and
// likewise for w, bias (null: none) and y; rows ldx / ldy apart within an item. The items'
// outputs must not overlap. One cuBLASLt launch (one per item where the strides' signs are
// mixed: see detail::cublaslt_strides); an erf GELU / SiLU (or a bias cuBLASLt cannot take) is
// one pass per item afterwards. Asynchronous on ctx's stream.
template <class T>
void linear_batched(Context& ctx, const T* x, std::int64_t ldx, const T* w, const T* bias, T* y, std::int64_t ldy,
                    std::int64_t M, std::int64_t N, std::int64_t K, const GemmBatch& batch,
                    Epilogue epi = Epilogue::None) {
  static_assert(is_device_float<T>, "linear_batched takes float or bf16");
  EPONA_CHECK(batch.count >= 1, "linear_batched: batch count ", batch.count);
  if (batch.count == 1) return linear(ctx, x, ldx, w, bias, y, ldy, M, N, K, epi);
  detail::check_product_extent("linear_batched", M, N, K, ldx, ldy);
  if (M == 0) return;
  // Items writing the same elements would race inside the one launch.
  EPONA_CHECK(std::llabs(batch.y) >= (M - 1) * ldy + N, "linear_batched: output items ", batch.y,
              " elements apart overlap (", M, " rows ", ldy, " apart, ", N, " wide)");
  GemmBatch b = batch;
  if (!bias) b.bias = 0;
  if (!detail::cublaslt_strides<T>(b)) {
    const std::int64_t last = b.count - 1;
    const auto at = [&](auto* p, std::int64_t stride, std::int64_t i) { return p ? detail::advance(p, i * stride) : p; };
    // Every stride <= 0: the same items from the last one, strides negated.
    if (detail::no_positive_stride(b))
      return linear_batched(ctx, at(x, b.x, last), ldx, at(w, b.w, last), at(bias, b.bias, last), at(y, b.y, last), ldy,
                            M, N, K, GemmBatch{b.count, -b.x, -b.w, -b.bias, -b.y}, epi);
    for (std::int64_t i = 0; i <= last; ++i)  // mixed signs or huge strides: one product per item
      linear(ctx, at(x, b.x, i), ldx, at(w, b.w, i), at(bias, b.bias, i), at(y, b.y, i), ldy, M, N, K, epi);
    return;
  }
  const std::int64_t bias_alignment = bias ? detail::batch_alignment(bias, b.bias) : 0;
  const cublasLtEpilogue_t wanted = detail::wanted_epilogue(epi, bias != nullptr, bias_alignment);
  const auto key = detail::batched_key(M, N, K, ldx, ldy, wanted, x, w, y, b);
  detail::LtPlan& plan = detail::plan_for(ctx, key, wanted, b, x, w, bias, y);
  detail::apply_batch(plan, b);
  detail::run_plan(ctx, plan, x, w, bias, y);
  for (std::int32_t i = 0; i < b.count; ++i)
    detail::finish_epilogue(ctx, plan, epi, detail::advance(y, i * b.y), ldy, M, N,
                            bias ? detail::advance(bias, i * b.bias) : bias);
}

// Layers of one shape on M rows each: y_i = act(x_i · w_iᵀ + b_i), x_i = x + i·x_stride and
// y_i = y + i·y_stride (elements; x_stride 0: one input for all), as one batched product whose
// weight (bias) stride is the distance w_1 - w_0 (b_1 - b_0). One product per layer where the
// weights (biases) do not lie equally far apart, in whole elements, or only some layers have a
// bias (Linear::bind_stacked keeps them in order, one matrix apart).
template <class T>
void linear_group(Context& ctx, const T* x, std::int64_t ldx, std::int64_t x_stride, const std::vector<const T*>& w,
                  const std::vector<const T*>& b, T* y, std::int64_t ldy, std::int64_t y_stride, std::int64_t M,
                  std::int64_t N, std::int64_t K, Epilogue epi = Epilogue::None) {
  const std::size_t count = w.size();
  EPONA_CHECK(count >= 1 && b.size() == count, "linear_group: ", count, " weights and ", b.size(), " biases");
  const auto equally_apart = [count](const std::vector<const T*>& p) -> std::optional<std::int64_t> {
    if (count == 1 || p[0] == nullptr) return std::int64_t{0};
    const auto step = detail::element_distance(p[0], p[1]);
    for (std::size_t i = 1; step && i < count; ++i)
      if (p[i] == nullptr || detail::element_distance(p[i - 1], p[i]) != step) return std::nullopt;
    return step;
  };
  const bool biases_alike =
      std::all_of(b.begin(), b.end(), [&](const T* p) { return (p == nullptr) == (b[0] == nullptr); });
  const auto w_stride = equally_apart(w), b_stride = equally_apart(b);
  if (count > 1 && w_stride && b_stride && biases_alike)
    return linear_batched(ctx, x, ldx, w[0], b[0], y, ldy, M, N, K,
                          GemmBatch{static_cast<std::int32_t>(count), x_stride, *w_stride, *b_stride, y_stride}, epi);
  for (std::size_t i = 0; i < count; ++i) {
    const auto at = static_cast<std::int64_t>(i);
    linear(ctx, x + at * x_stride, ldx, w[i], b[i], y + at * y_stride, ldy, M, N, K, epi);
  }
}

// Two layers of one shape: linear_group over the pair.
template <class T>
void linear_pair(Context& ctx, const T* x, std::int64_t ldx, std::int64_t x_stride, const T* w0, const T* b0,
                 const T* w1, const T* b1, T* y, std::int64_t ldy, std::int64_t y_stride, std::int64_t M,
                 std::int64_t N, std::int64_t K, Epilogue epi = Epilogue::None) {
  linear_group(ctx, x, ldx, x_stride, {w0, w1}, {b0, b1}, y, ldy, y_stride, M, N, K, epi);
}

}  // namespace epona::cuda
