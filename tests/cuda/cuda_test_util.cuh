// Shared helpers of the GPU tests (tests/cuda/*.cu): skip without a GPU, random inputs,
// bf16 rounding of host data, upload/download with conversion, output poisoning, and the
// error measures every cross-backend check reports (relative L2 and scale-relative max).
#pragma once

#include <doctest/doctest.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/cpu/ops.hpp"
#include "epona/cuda/ops.cuh"
#include "../ops/names.hpp"  // epilogue_name

// Every GPU test case starts with this: on a machine without a GPU it passes with a message.
#define EPONA_REQUIRE_GPU()                    \
  do {                                         \
    if (!::epona::cuda::has_gpu()) {           \
      MESSAGE("no CUDA device: skipping");     \
      return;                                  \
    }                                          \
  } while (0)

namespace epona::test {

// True where the machine has two GPUs; else the case skips with a message naming `what` needs them.
inline bool two_gpus(const char* what) {
  int gpus = 0;
  EPONA_CUDA_CHECK(cudaGetDeviceCount(&gpus));
  if (gpus < 2) MESSAGE("one GPU: ", what, " needs two, skipping");
  return gpus >= 2;
}

// Sets one field of a context's kernel policy (ctx.policy().field) while alive, then restores
// its previous value.
template <class Value>
struct ScopedPolicy {
  Value& field;
  Value before;
  ScopedPolicy(Value& f, Value v) : field(f), before(f) { field = v; }
  ~ScopedPolicy() { field = before; }
  ScopedPolicy(const ScopedPolicy&) = delete;
  ScopedPolicy& operator=(const ScopedPolicy&) = delete;
};

using HostF = Tensor<float, Cpu>;
template <class T> using Dev = Tensor<T, Cuda>;

inline const char* type_name(float*) { return "f32"; }
inline const char* type_name(bf16*) { return "bf16"; }
template <class T> const char* type_name() { return type_name(static_cast<T*>(nullptr)); }

// Uniform values in [lo, hi); a fresh generator per call so each case has its own data.
inline HostF random_tensor(Shape shape, std::uint32_t seed, float lo = -1.f, float hi = 1.f) {
  HostF t(std::move(shape));
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> dist(lo, hi);
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = dist(gen);
  return t;
}

// Rounds every value to what T can hold (bf16: nearest even), in place; returns t.
template <class T>
HostF& round_to(HostF& t) {
  if constexpr (std::is_same_v<T, bf16>)
    for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = float(bf16(t.data()[i]));
  return t;
}

// Converts to T and copies to the device. offset > 0 places the data `offset` elements into
// a larger allocation, so the tensor is deliberately misaligned (alignment fallbacks).
template <class T>
Dev<T> upload(cuda::Context& ctx, const HostF& src, std::int64_t offset = 0) {
  Tensor<T, Cpu> host(src.shape());
  for (std::int64_t i = 0; i < src.numel(); ++i) host.data()[i] = T(src.data()[i]);
  if (offset == 0) return cuda::to_device(ctx, host);
  Dev<T> block({src.numel() + offset});
  auto view = Dev<T>::view(block.data() + offset, src.shape(), block.storage());
  cuda::copy(ctx, view, host);
  return view;
}

template <class T>
HostF download(cuda::Context& ctx, const Dev<T>& src) {
  const auto host = cuda::to_host(ctx, src);
  HostF out(src.shape());
  for (std::int64_t i = 0; i < src.numel(); ++i) out.data()[i] = float(host.data()[i]);
  return out;
}

// NaN in both float32 and bf16: an element the kernel failed to write stays NaN.
template <class T>
void poison(cuda::Context& ctx, Dev<T>& t) {
  cuda::fill_bytes(ctx, t, 0xFF);
}

struct Diff {
  double rel_l2 = 0, max_abs = 0, max_ref = 0;
  std::int64_t nans = 0, n = 0;
};

// Compares out with ref over the elements where `keep(i)` (default: all).
template <class Keep>
Diff measure(const float* out, const float* ref, std::int64_t n, Keep keep) {
  Diff e;
  double num = 0, den = 0;
  for (std::int64_t i = 0; i < n; ++i) {
    if (!keep(i)) continue;
    ++e.n;
    if (!std::isfinite(out[i])) {
      ++e.nans;
      continue;
    }
    const double d = double(out[i]) - double(ref[i]);
    num += d * d;
    den += double(ref[i]) * ref[i];
    e.max_abs = std::max(e.max_abs, std::abs(d));
    e.max_ref = std::max(e.max_ref, std::abs(double(ref[i])));
  }
  e.rel_l2 = den > 0 ? std::sqrt(num / den) : std::sqrt(num);
  return e;
}
inline Diff measure(const HostF& out, const HostF& ref) {
  REQUIRE(out.numel() == ref.numel());
  return measure(out.data(), ref.data(), out.numel(), [](std::int64_t) { return true; });
}

// How many of the elements where `keep(i)` (default: all) differ between a and b bit for bit
// (the checks of paths that must round exactly alike).
template <class Keep>
std::int64_t count_bit_differences(const float* a, const float* b, std::int64_t n, Keep keep) {
  std::int64_t differ = 0;
  for (std::int64_t i = 0; i < n; ++i) differ += keep(i) && std::memcmp(a + i, b + i, sizeof(float)) != 0;
  return differ;
}
inline std::int64_t count_bit_differences(const HostF& a, const HostF& b) {
  REQUIRE(a.numel() == b.numel());
  return count_bit_differences(a.data(), b.data(), a.numel(), [](std::int64_t) { return true; });
}

// bf16 keeps 8 significant bits: rounding to it moves a value by at most 2^-8 of itself.
inline constexpr double kBf16Roundoff = 1.0 / 256;
// float32 paths must match the CPU to float32 rounding (accumulation order only).
inline constexpr double kF32Tol = 1e-5;

// A check passes when ‖out − ref‖₂ / ‖ref‖₂ <= rel and max |out − ref| <= abs.
struct Bound {
  double rel;
  double abs;
};

inline void check_error(const Diff& e, const Bound& b, const std::string& what) {
  std::printf("  %-58s rel_l2 %.2e  max_abs %.2e  (bounds %.1e, %.1e; n %lld)\n", what.c_str(), e.rel_l2, e.max_abs,
              b.rel, b.abs, static_cast<long long>(e.n));
  INFO(what, ": rel_l2 ", e.rel_l2, " max_abs ", e.max_abs, " bounds ", b.rel, ", ", b.abs, " nans ", e.nans);
  CHECK(e.n > 0);
  CHECK(e.nans == 0);
  CHECK(e.rel_l2 <= b.rel);
  CHECK(e.max_abs <= b.abs);
}

// The result rounded once to T: float32 within 1e-5; bf16 within 2^-8 of each value (plus
// float32 accumulation-order differences).
template <class T>
Bound one_rounding(double max_ref) {
  if constexpr (std::is_same_v<T, float>) return {kF32Tol, kF32Tol * max_ref};
  return {kBf16Roundoff, (kBf16Roundoff + kF32Tol) * max_ref};
}

inline double norm2(const HostF& t) {
  double s = 0;
  for (std::int64_t i = 0; i < t.numel(); ++i) s += double(t.data()[i]) * t.data()[i];
  return std::sqrt(s);
}

inline double max_abs(const HostF& t) {
  double m = 0;
  for (std::int64_t i = 0; i < t.numel(); ++i) m = std::max(m, double(std::abs(t.data()[i])));
  return m;
}

// Tensor parallelism (tests/cuda/dit_shards.cu, world_parity.cu): every shard's result against the
// whole model's (`whole`, same dtype) and the whole float32 model's (`f32`). float32: within 1e-5
// relative L2 of the whole. bf16: the distance to float32 at most 1.5x the whole bf16 model's own,
// plus 4e-3 (a shard rounds its partial outputs to bf16 before the sum: one more rounding per summed
// layer, each within 2^-8 of its value). Every shard the same bits, and finite.
template <class W>
void check_shard_results(const std::vector<HostF>& parts, const HostF& whole, const HostF& f32, const std::string& what) {
  const double whole_err = measure(whole, f32).rel_l2;
  for (std::size_t r = 0; r < parts.size(); ++r) {
    const Diff d = measure(parts[r], whole), to_f32 = measure(parts[r], f32);
    CHECK(d.nans == 0);
    CHECK(count_bit_differences(parts[r], parts[0]) == 0);
    if (r == 0)
      MESSAGE(what, ": rel L2 to the whole model ", d.rel_l2, ", to the whole float32 model ", to_f32.rel_l2,
              " (the whole model's: ", whole_err, ")");
    if constexpr (std::is_same_v<W, float>)
      CHECK(d.rel_l2 <= 1e-5);
    else
      CHECK(to_f32.rel_l2 <= 1.5 * whole_err + 4e-3);
  }
}

}  // namespace epona::test
