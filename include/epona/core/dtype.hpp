// epona/core/dtype.hpp — element types: float32, bfloat16 (round-to-nearest-even),
// float16 (for checkpoints: read, and written by `epona convert --dtype float16`) and int64, plus the run-time DType tag that
// file readers report.
#pragma once

#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "epona/core/error.hpp"

#if defined(__CUDACC__)
#define EPONA_HOST_DEVICE __host__ __device__
#else
#define EPONA_HOST_DEVICE
#endif

namespace epona {

// bfloat16 stored as its 16 raw bits. Conversion from float rounds to nearest even;
// NaN stays NaN (quiet). Layout-compatible with __nv_bfloat16.
struct bf16 {
  std::uint16_t bits = 0;

  bf16() = default;
  EPONA_HOST_DEVICE explicit bf16(float f) : bits(from_float(f)) {}
  EPONA_HOST_DEVICE explicit operator float() const { return to_float(bits); }

  EPONA_HOST_DEVICE static std::uint16_t from_float(float f) {
    std::uint32_t u;
    std::memcpy(&u, &f, sizeof u);
    if ((u & 0x7fffffffu) > 0x7f800000u) return static_cast<std::uint16_t>((u >> 16) | 0x0040u);
    const std::uint32_t rounding = 0x7fffu + ((u >> 16) & 1u);
    return static_cast<std::uint16_t>((u + rounding) >> 16);
  }
  EPONA_HOST_DEVICE static float to_float(std::uint16_t b) {
    const std::uint32_t u = static_cast<std::uint32_t>(b) << 16;
    float f;
    std::memcpy(&f, &u, sizeof f);
    return f;
  }
  static bf16 from_bits(std::uint16_t b) {
    bf16 r;
    r.bits = b;
    return r;
  }
};

// IEEE half -> float (exact). Only needed to read fp16 checkpoints.
inline float half_to_float(std::uint16_t h) {
  const std::uint32_t sign = static_cast<std::uint32_t>(h & 0x8000u) << 16;
  const std::uint32_t exp = (h >> 10) & 0x1fu;
  const std::uint32_t man = h & 0x3ffu;
  std::uint32_t u;
  if (exp == 0) {
    if (man == 0) {
      u = sign;
    } else {  // subnormal: value = man * 2^-24
      const float f = std::ldexp(static_cast<float>(man), -24);
      std::memcpy(&u, &f, sizeof u);
      u |= sign;
    }
  } else if (exp == 31) {
    u = sign | 0x7f800000u | (man << 13);
  } else {
    u = sign | ((exp + 112u) << 23) | (man << 13);
  }
  float f;
  std::memcpy(&f, &u, sizeof f);
  return f;
}

// float -> IEEE half, rounded to nearest even (as the hardware and torch's .half() do): beyond
// half's range (|f| >= 65520) it becomes inf; NaN stays NaN (quiet). For writing fp16 checkpoints.
inline std::uint16_t float_to_half(float f) {
  std::uint32_t u;
  std::memcpy(&u, &f, sizeof u);
  const auto sign = static_cast<std::uint16_t>((u >> 16) & 0x8000u);
  const std::uint32_t a = u & 0x7fffffffu;
  if (a > 0x7f800000u) return static_cast<std::uint16_t>(sign | 0x7e00u | ((a >> 13) & 0x3ffu));
  if (a >= 0x47800000u) return static_cast<std::uint16_t>(sign | 0x7c00u);  // >= 2^16, and inf
  const std::uint32_t e = a >> 23;
  std::uint32_t h, rem, halfway;
  if (e >= 113) {  // a normal half: rebias the exponent (127 -> 15), drop 13 mantissa bits
    h = (a - 0x38000000u) >> 13, rem = a & 0x1fffu, halfway = 0x1000u;
  } else {  // a subnormal half (units of 2^-24), or zero below 2^-25
    if (e < 102) return sign;
    const std::uint32_t m = (a & 0x7fffffu) | 0x800000u, shift = 126 - e;
    h = m >> shift, rem = m & ((1u << shift) - 1), halfway = 1u << (shift - 1);
  }
  if (rem > halfway || (rem == halfway && (h & 1u))) ++h;  // a carry into the exponent is right (up to inf)
  return static_cast<std::uint16_t>(sign | h);
}

enum class DType : std::uint8_t { F32, BF16, F16, I64 };

inline std::size_t dtype_size(DType t) {
  switch (t) {
    case DType::F32: return 4;
    case DType::BF16: return 2;
    case DType::F16: return 2;
    case DType::I64: return 8;
  }
  return 0;
}

inline std::string_view dtype_name(DType t) {
  switch (t) {
    case DType::F32: return "float32";
    case DType::BF16: return "bfloat16";
    case DType::F16: return "float16";
    case DType::I64: return "int64";
  }
  return "?";
}

template <class T> struct dtype_of;
template <> struct dtype_of<float> { static constexpr DType value = DType::F32; };
template <> struct dtype_of<bf16> { static constexpr DType value = DType::BF16; };
template <> struct dtype_of<std::int64_t> { static constexpr DType value = DType::I64; };

// Reads element i of a raw little-endian buffer of dtype t as float (checkpoint conversion).
inline float load_as_float(const void* data, DType t, std::size_t i) {
  const auto* p = static_cast<const unsigned char*>(data);
  switch (t) {
    case DType::F32: { float f; std::memcpy(&f, p + 4 * i, 4); return f; }
    case DType::BF16: { std::uint16_t b; std::memcpy(&b, p + 2 * i, 2); return bf16::to_float(b); }
    case DType::F16: { std::uint16_t h; std::memcpy(&h, p + 2 * i, 2); return half_to_float(h); }
    case DType::I64: { std::int64_t v; std::memcpy(&v, p + 8 * i, 8); return static_cast<float>(v); }
  }
  fail("load_as_float: unknown dtype");
}

}  // namespace epona
