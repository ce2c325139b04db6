// Tests for epona/cpu/simd.hpp: the tail handling every kernel relies on (partial loads and
// stores, map over any length, masked sums), the lane shuffles of RoPE and the reductions.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <numeric>

#include "epona/core/dtype.hpp"
#include "epona/cpu/simd.hpp"
#include "testing.hpp"

using namespace epona::cpu;
using simd::Batch;
using simd::kWidth;

TEST_CASE("partial loads fill, partial stores stop at n") {
  std::vector<float> src(kWidth);
  std::iota(src.begin(), src.end(), 1.f);
  for (std::int64_t n = 0; n < kWidth; ++n) {
    alignas(64) float out[kWidth];
    simd::load_partial(src.data(), n, -7.f).store_aligned(out);
    for (std::int64_t i = 0; i < kWidth; ++i) CHECK(out[i] == (i < n ? src[i] : -7.f));
    std::vector<float> dst(kWidth, 0.f);
    simd::store_partial(dst.data(), simd::load(src.data()), n);
    for (std::int64_t i = 0; i < kWidth; ++i) CHECK(dst[i] == (i < n ? src[i] : 0.f));
  }
}

TEST_CASE("map touches exactly n elements, any n, several inputs") {
  for (std::int64_t n : {0, 1, 3, 15, 16, 17, 40, 100}) {
    const auto a = epona::test::random_floats(static_cast<std::size_t>(n + 8), 1);
    const auto b = epona::test::random_floats(static_cast<std::size_t>(n + 8), 2);
    std::vector<float> y(static_cast<std::size_t>(n + 8), 42.f);
    simd::map(n, y.data(), [](const Batch& x, const Batch& z) { return x * z + Batch(1.f); }, a.data(), b.data());
    for (std::int64_t i = 0; i < n + 8; ++i) CHECK(y[i] == (i < n ? a[i] * b[i] + 1.f : 42.f));
  }
}

TEST_CASE("sum_of ignores the padding lanes even when f(0) != 0") {
  for (std::int64_t n : {1, 5, 16, 17, 63, 64, 65, 1000}) {
    const auto x = epona::test::random_floats(static_cast<std::size_t>(n), 3);
    double ref = 0, ref_shift = 0;
    for (float v : x) {
      ref += v;
      ref_shift += (v - 2.0) * (v - 2.0);
    }
    CHECK(simd::sum(x.data(), n) == doctest::Approx(ref).epsilon(1e-6));
    const Batch two(2.f);
    CHECK(simd::sum_of(x.data(), n, [two](const Batch& v) { return (v - two) * (v - two); }) ==
          doctest::Approx(ref_shift).epsilon(1e-6));
  }
}

TEST_CASE("swap_pairs, dup_pairs, alternating_signs, reductions") {
  alignas(64) float in[kWidth], out[kWidth];
  std::iota(in, in + kWidth, 0.f);
  const Batch v = Batch::load_aligned(in);
  simd::swap_pairs(v).store_aligned(out);
  for (std::int64_t i = 0; i < kWidth; ++i) CHECK(out[i] == in[i ^ 1]);
  simd::dup_pairs(v).store_aligned(out);
  for (std::int64_t i = 0; i < kWidth; ++i) CHECK(out[i] == in[i / 2]);
  simd::alternating_signs().store_aligned(out);
  for (std::int64_t i = 0; i < kWidth; ++i) CHECK(out[i] == (i % 2 ? 1.f : -1.f));
  CHECK(simd::reduce_add(v) == doctest::Approx(kWidth * (kWidth - 1) / 2.0));
  CHECK(simd::reduce_max(v) == static_cast<float>(kWidth - 1));
  CHECK(simd::reduce_max(Batch(-std::numeric_limits<float>::infinity())) == -std::numeric_limits<float>::infinity());
}

TEST_CASE("parallel_map and for_each_row cover every element once") {
  const std::int64_t n = (1 << 16) + 13;
  std::vector<float> x(static_cast<std::size_t>(n), 1.f);
  simd::parallel_map(n, x.data(), [](const Batch& v) { return v + Batch(1.f); }, x.data());
  for (float v : x) REQUIRE(v == 2.f);
  std::vector<int> hits(1000, 0);
  simd::for_each_row(1000, 1 << 10, [&](std::int64_t r) { hits[static_cast<std::size_t>(r)] += 1; });
  for (int h : hits) REQUIRE(h == 1);
}

TEST_CASE("load_bf16_pairs widens even and odd elements exactly") {
  std::vector<std::uint16_t> bits(static_cast<std::size_t>(2 * kWidth));
  const auto v = epona::test::random_floats(bits.size(), 9, -100.f, 100.f);
  for (std::size_t i = 0; i < bits.size(); ++i) bits[i] = epona::bf16::from_float(v[i]);
  Batch even, odd;
  simd::load_bf16_pairs(bits.data(), even, odd);
  alignas(64) float e[kWidth], o[kWidth];
  even.store_aligned(e);
  odd.store_aligned(o);
  for (std::int64_t i = 0; i < kWidth; ++i) {
    CHECK(e[i] == epona::bf16::to_float(bits[static_cast<std::size_t>(2 * i)]));
    CHECK(o[i] == epona::bf16::to_float(bits[static_cast<std::size_t>(2 * i + 1)]));
  }
}
