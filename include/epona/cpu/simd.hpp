// epona/cpu/simd.hpp — the few SIMD primitives the CPU kernels use, over xsimd's widest
// float batch for the compile target (AVX-512 here, AVX2/SSE elsewhere). Wraps the names that
// changed after xsimd 8.1 (hadd -> reduce_add, ...) and gives every kernel one way to do tails.
#pragma once

// GCC 12 flags its own _mm512_undefined_* intrinsics (`__m512i __Y = __Y;`) as uninitialised
// wherever xsimd's math inlines them: a known false positive, silenced for xsimd only.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#endif
#include <xsimd/xsimd.hpp>
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <new>

namespace epona::cpu::simd {

using Batch = xsimd::batch<float>;
using Arch = Batch::arch_type;
inline constexpr std::int64_t kWidth = static_cast<std::int64_t>(Batch::size);

inline Batch load(const float* p) { return Batch::load_unaligned(p); }
inline void store(float* p, const Batch& v) { v.store_unaligned(p); }

// Loads n < kWidth floats, the other lanes set to `fill` (0 for sums, -inf for maxima).
inline Batch load_partial(const float* p, std::int64_t n, float fill = 0.f) {
  alignas(64) float buf[kWidth];
  std::fill_n(buf, kWidth, fill);
  std::copy_n(p, n, buf);
  return Batch::load_aligned(buf);
}
inline void store_partial(float* p, const Batch& v, std::int64_t n) {
  alignas(64) float buf[kWidth];
  v.store_aligned(buf);
  std::copy_n(buf, n, p);
}

// Loads a batch that the caller reuses several times. GCC otherwise folds the load into every
// FMA that reads it (one memory operand each), which makes register-blocked kernels bound on
// load bandwidth instead of FMA throughput; the empty asm pins the value in a register.
inline Batch load_reused(const float* p) {
  Batch v = Batch::load_unaligned(p);
#if defined(__GNUC__) && defined(__AVX512F__)
  asm("" : "+v"(v.data));  // any of the 32 vector registers
#elif defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
  asm("" : "+x"(v.data));
#endif
  return v;
}

// 2·kWidth bfloat16 values (raw bits) widened to float: lanes of `even` hold elements 0, 2, 4..
// and `odd` elements 1, 3, 5.. (a bf16 is the high half of a float, so a 32-bit lane holding
// two of them gives the odd one by masking and the even one by shifting). No shuffles needed;
// the other operand of a dot product is split into even/odd halves once instead.
inline void load_bf16_pairs(const std::uint16_t* bits, Batch& even, Batch& odd) {
  using U = xsimd::batch<std::uint32_t, Arch>;
  const U u = U::load_unaligned(reinterpret_cast<const std::uint32_t*>(bits));
  even = xsimd::bitwise_cast<Batch>(u << 16);
  odd = xsimd::bitwise_cast<Batch>(u & U(0xffff0000u));
}

// Horizontal reductions (xsimd 8.1 has hadd; newer releases call it reduce_add; 8.1 has no
// horizontal max, so that one goes through memory — it runs once per row).
inline float reduce_add(const Batch& v) { return xsimd::hadd(v); }
inline float reduce_max(const Batch& v) {
  alignas(64) float buf[kWidth];
  v.store_aligned(buf);
  return *std::max_element(buf, buf + kWidth);
}

// Swaps neighbouring lanes (0<->1, 2<->3, ...): the partner of each interleaved RoPE pair.
struct SwapPairsIndex {
  static constexpr std::uint32_t get(std::size_t i, std::size_t) { return static_cast<std::uint32_t>(i ^ 1u); }
};
inline Batch swap_pairs(const Batch& v) {
  return xsimd::swizzle(v, xsimd::make_batch_constant<xsimd::batch<std::uint32_t, Arch>, SwapPairsIndex>());
}
// Repeats each lane of the lower half twice: (v0, v0, v1, v1, ...), a per-pair table per channel.
struct DupPairsIndex {
  static constexpr std::uint32_t get(std::size_t i, std::size_t) { return static_cast<std::uint32_t>(i / 2); }
};
inline Batch dup_pairs(const Batch& v) {
  return xsimd::swizzle(v, xsimd::make_batch_constant<xsimd::batch<std::uint32_t, Arch>, DupPairsIndex>());
}
// (-1, +1, -1, +1, ...): the signs of the sine terms of a 2-D rotation on interleaved pairs.
inline Batch alternating_signs() {
  alignas(64) float s[kWidth];
  for (std::int64_t i = 0; i < kWidth; ++i) s[i] = (i % 2) ? 1.f : -1.f;
  return Batch::load_aligned(s);
}

// y[i] = f(a[i], b[i], ...) for i < n, f a function of Batches. The tail goes through padded
// batches, so every element takes the same code path whatever its position. y may alias inputs.
template <class F, class... In>
inline void map(std::int64_t n, float* y, F&& f, const In*... in) {
  std::int64_t i = 0;
  for (; i + kWidth <= n; i += kWidth) store(y + i, f(load(in + i)...));
  if (i < n) store_partial(y + i, f(load_partial(in + i, n - i)...), n - i);
}

// Sum of x[0..n) with four independent accumulators (more accurate and faster than one).
template <class F>
inline float sum_of(const float* x, std::int64_t n, F&& f) {
  Batch a0(0.f), a1(0.f), a2(0.f), a3(0.f);
  std::int64_t i = 0;
  for (; i + 4 * kWidth <= n; i += 4 * kWidth) {
    a0 += f(load(x + i));
    a1 += f(load(x + i + kWidth));
    a2 += f(load(x + i + 2 * kWidth));
    a3 += f(load(x + i + 3 * kWidth));
  }
  for (; i + kWidth <= n; i += kWidth) a0 += f(load(x + i));
  if (i < n) {
    // Padding lanes must contribute 0 after f: mask them out explicitly.
    alignas(64) float idx[kWidth];
    for (std::int64_t l = 0; l < kWidth; ++l) idx[l] = static_cast<float>(l);
    const auto valid = Batch::load_aligned(idx) < Batch(static_cast<float>(n - i));
    a1 += xsimd::select(valid, f(load_partial(x + i, n - i)), Batch(0.f));
  }
  return reduce_add((a0 + a1) + (a2 + a3));
}
inline float sum(const float* x, std::int64_t n) {
  return sum_of(x, n, [](const Batch& v) { return v; });
}

// A 64-byte aligned float array (per-thread scratch of the tiled kernels).
class AlignedFloats {
 public:
  AlignedFloats() = default;
  explicit AlignedFloats(std::int64_t n)
      : p_(static_cast<float*>(::operator new[](static_cast<std::size_t>(std::max<std::int64_t>(n, 1)) * sizeof(float),
                                                std::align_val_t(64)))) {}
  float* data() const { return p_.get(); }
  float& operator[](std::int64_t i) const { return p_.get()[i]; }

 private:
  struct Free {
    void operator()(float* p) const { ::operator delete[](p, std::align_val_t(64)); }
  };
  std::unique_ptr<float[], Free> p_;
};

// Below this many elements a kernel runs on the calling thread (an OpenMP fork costs ~µs).
inline constexpr std::int64_t kParallelMin = 1 << 15;

// map() over [0, n) in chunks shared among the OpenMP threads (serial when n is small).
template <class F, class... In>
inline void parallel_map(std::int64_t n, float* y, F f, const In*... in) {
  constexpr std::int64_t chunk = 1 << 12;
  const std::int64_t chunks = (n + chunk - 1) / chunk;
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (std::int64_t c = 0; c < chunks; ++c) map(std::min(chunk, n - c * chunk), y + c * chunk, f, (in + c * chunk)...);
}

// Runs row(r) for r < rows, in parallel when the whole job (rows × width) is large.
template <class RowFn>
inline void for_each_row(std::int64_t rows, std::int64_t width, RowFn row) {
#pragma omp parallel for schedule(static) if (rows * width >= kParallelMin && rows > 1)
  for (std::int64_t r = 0; r < rows; ++r) row(r);
}

}  // namespace epona::cpu::simd
