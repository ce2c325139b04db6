// Tests for epona/core/tensor.hpp and epona/core/dtype.hpp.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>

#include "epona/core/dtype.hpp"
#include "epona/core/tensor.hpp"

using namespace epona;

TEST_CASE("tensor shape, reshape, slice and index") {
  Tensor<float> t({2, 3, 4});
  for (int i = 0; i < 24; ++i) t.data()[i] = float(i);
  CHECK(t.numel() == 24);
  CHECK(t.size(-1) == 4);
  CHECK(t.at(1, 2, 3) == 23.f);
  auto r = t.reshape({6, -1});
  CHECK(r.shape() == Shape{6, 4});
  CHECK(r.data() == t.data());
  auto s = t.slice(1, 2);
  CHECK(s.shape() == Shape{1, 3, 4});
  CHECK(s.at(0, 0, 0) == 12.f);
  CHECK(t[1].at(1, 1) == 17.f);
  CHECK_THROWS_AS(t.reshape({5, 5}), Error);
  CHECK_THROWS_AS(t.slice(1, 3), Error);
  CHECK_THROWS_AS(t.at(2, 0, 0), Error);
  CHECK_THROWS_WITH_AS(t.size(3), doctest::Contains("out of range"), Error);
  CHECK_THROWS_AS(Tensor<float>({-1, 2}), Error);
  CHECK_THROWS_AS(Tensor<float>({INT64_MAX, 4}), Error);
  // 2^62 elements fit int64, but 2^62 floats are 2^64 bytes (0 in a size_t): refused, not 0 bytes
  CHECK_THROWS_WITH_AS(Tensor<float>({std::int64_t{1} << 31, std::int64_t{1} << 31}), doctest::Contains("needs more than"), Error);
  CHECK_THROWS_WITH_AS(Tensor<double>({std::int64_t{1} << 61}), doctest::Contains("needs more than"), Error);
  // a size that fits but cannot be allocated is epona's out-of-memory error, not std::bad_alloc
  CHECK_THROWS_WITH_AS(Tensor<float>({std::int64_t{1} << 60}), doctest::Contains("out of host memory"), Error);
}

TEST_CASE("clone is deep, copies are handles") {
  auto a = Tensor<float>::full({3}, 1.f);
  auto b = a;
  auto c = a.clone();
  a.data()[0] = 5.f;
  CHECK(b.at(0) == 5.f);
  CHECK(c.at(0) == 1.f);
}

TEST_CASE("bfloat16 rounds to nearest even and keeps NaN") {
  CHECK(bf16(1.0f).bits == 0x3f80);
  // 1 + 2^-8 is exactly halfway between 1 and 1 + 2^-7: ties to even (1.0).
  CHECK(bf16(1.0f + std::ldexp(1.0f, -8)).bits == 0x3f80);
  // 1 + 3*2^-8 is halfway between 1+2^-7 (odd) and 1+2^-6 (even): rounds up.
  CHECK(bf16(1.0f + 3 * std::ldexp(1.0f, -8)).bits == 0x3f82);
  CHECK(bf16(1.0f + std::ldexp(1.0f, -8) + std::ldexp(1.0f, -20)).bits == 0x3f81);
  CHECK(std::isnan(float(bf16(std::numeric_limits<float>::quiet_NaN()))));
  CHECK(float(bf16(std::numeric_limits<float>::infinity())) == std::numeric_limits<float>::infinity());
  CHECK(float(bf16(-2.5f)) == -2.5f);
  // Largest finite float rounds up to infinity, as in PyTorch.
  CHECK(std::isinf(float(bf16(std::numeric_limits<float>::max()))));
}

TEST_CASE("float16 to float32 is exact") {
  CHECK(half_to_float(0x3c00) == 1.0f);
  CHECK(half_to_float(0xc000) == -2.0f);
  CHECK(half_to_float(0x0001) == std::ldexp(1.0f, -24));
  CHECK(half_to_float(0x7bff) == 65504.0f);
  CHECK(std::isinf(half_to_float(0x7c00)));
  CHECK(std::isnan(half_to_float(0x7e00)));
}

TEST_CASE("float_to_half rounds to nearest even and inverts half_to_float") {
  for (std::uint32_t h = 0; h < 0x10000; ++h) {  // every half that is not NaN comes back unchanged
    const auto bits = static_cast<std::uint16_t>(h);
    if ((bits & 0x7c00u) == 0x7c00u && (bits & 0x3ffu)) continue;
    REQUIRE_MESSAGE(float_to_half(half_to_float(bits)) == bits, "half bits ", h);
  }
  // Halfway between two halves goes to the even one; a hair above goes up.
  CHECK(float_to_half(1.0f + std::ldexp(1.0f, -11)) == 0x3c00);
  CHECK(float_to_half(1.0f + 3 * std::ldexp(1.0f, -11)) == 0x3c02);
  CHECK(float_to_half(1.0f + std::ldexp(1.0f, -11) + std::ldexp(1.0f, -20)) == 0x3c01);
  CHECK(float_to_half(std::ldexp(1.0f, -25)) == 0x0000);      // halfway to the smallest subnormal: even
  CHECK(float_to_half(std::ldexp(3.0f, -26)) == 0x0001);      // above halfway
  CHECK(float_to_half(std::ldexp(3.0f, -25)) == 0x0002);      // 1.5 units: even (2)
  CHECK(float_to_half(65519.0f) == 0x7bff);                   // below the halfway point to 2^16
  CHECK(float_to_half(65520.0f) == 0x7c00);                   // halfway: rounds to even, which is inf
  CHECK(float_to_half(-1e30f) == 0xfc00);
  CHECK(float_to_half(-0.0f) == 0x8000);
  CHECK(std::isnan(half_to_float(float_to_half(std::numeric_limits<float>::quiet_NaN()))));
}
