// The bf16-weight CPU path's tolerance (epona/cpu/gemm.hpp with AVX512-BF16 dot products):
// weights stored bf16 (exact), activations rounded to bf16 (round to nearest even) while
// packing, products exact, sums in float32. Stated bound, per output element:
//   |ŷ − y| <= ε_K · (Σ_k |x_k·w_k| + |b|),   ε_K = 2^-8 + (K + 8)·2^-23
// against y, the exact product of the float32 activations with the bf16 weights: 2^-8 is the
// rounding of x (unit roundoff of bf16's 8-bit significand), (K + 8)·2^-24 the float32
// accumulation (K products, one sum per K block, the bias) of the bf16 path, and as much again
// for the float32 path it is compared with. Typical error: x's rounding errors are independent,
// so the error over sqrt(Σ (x_k·w_k)²) has an RMS of at most 2^-8/√3 ≈ 0.0023.
// Checked: (1) against a float64 emulation of exactly that arithmetic, within the float32
// accumulation term alone (so nothing but the rounding of x differs); (2) the bound against
// float64 and against the float32 path; (3) the RMS, between 0.2 and 1.1 times 2^-8/√3 (the
// lower limit shows the activations really are rounded, i.e. the dot-product path ran).
#include <doctest/doctest.h>

#include <cmath>
#include <vector>

#include "epona/cpu/gemm.hpp"
#include "testing.hpp"

using namespace epona;

namespace {

double eps_bf16_path(std::int64_t K) { return 0x1p-8 + (double(K) + 8) * 0x1p-23; }

struct Case {
  std::int64_t M, N, K;
};

struct Data {
  std::vector<float> x, b;
  std::vector<bf16> w;
};

Data make(const Case& c, std::uint32_t seed) {
  Data d;
  d.x = test::random_floats(static_cast<std::size_t>(c.M * c.K), seed, -2.f, 2.f);
  const auto wf = test::random_floats(static_cast<std::size_t>(c.N * c.K), seed + 1, -1.f, 1.f);
  d.w.resize(wf.size());
  for (std::size_t i = 0; i < wf.size(); ++i) d.w[i] = bf16(wf[i] / std::sqrt(float(c.K)));
  d.b = test::random_floats(static_cast<std::size_t>(c.N), seed + 2, -0.5f, 0.5f);
  return d;
}

std::vector<float> run(cpu::Isa isa, const Case& c, const Data& d, int threads) {
  cpu::ScopedIsa scoped(isa);
  cpu::Context ctx(threads);
  std::vector<bf16> b16(d.b.size());
  for (std::size_t i = 0; i < d.b.size(); ++i) b16[i] = bf16(d.b[i]);
  std::vector<float> y(static_cast<std::size_t>(c.M * c.N));
  cpu::linear<bf16>(ctx, d.x.data(), c.K, d.w.data(), b16.data(), y.data(), c.N, c.M, c.N, c.K);
  return y;
}

}  // namespace

TEST_CASE("bf16 weights with AVX512-BF16 dot products (and AMX where present): within the stated bound of float32") {
  if (!cpu::cpu_features().supports(cpu::Isa::Avx512Bf16)) {
    MESSAGE("this CPU has no AVX512-BF16: bf16 weights are widened to float32 (tested in gemm.cpp)");
    return;
  }
  const cpu::Isa f32_path = cpu::Isa::Avx512;  // the same weights widened: float32 arithmetic
  for (cpu::Isa bf16_path : {cpu::Isa::Avx512Bf16, cpu::Isa::Amx})
  for (const Case& c : {Case{131, 1024, 1024}, Case{15, 512, 2048}, Case{300, 200, 4096}, Case{7, 33, 5},
                        Case{64, 64, 1}, Case{29, 100, 999}})
    for (int threads : {1, 3}) {
      if (!cpu::cpu_features().supports(bf16_path)) continue;  // AMX: only where the CPU has it
      const Data d = make(c, static_cast<std::uint32_t>(c.K + c.N));
      const auto got = run(bf16_path, c, d, threads);
      const auto f32 = run(f32_path, c, d, threads);
      const double eps = eps_bf16_path(c.K);
      int outside_emulation = 0, outside_bound = 0, outside_vs_f32 = 0;
      double sq_err = 0, sq_norm = 0;
      for (std::int64_t m = 0; m < c.M; ++m)
        for (std::int64_t n = 0; n < c.N; ++n) {
          const double bias = double(float(bf16(d.b[n])));  // the bias is stored bf16 as well
          double exact = bias, emulated = bias, mag = 0, sq = 0;
          for (std::int64_t k = 0; k < c.K; ++k) {
            const double x = d.x[m * c.K + k], w = double(float(d.w[n * c.K + k]));
            const double x16 = double(float(bf16(d.x[m * c.K + k])));
            exact += x * w;
            emulated += x16 * w;
            mag += std::abs(x * w);
            sq += x * w * x * w;
          }
          const double scale = mag + std::abs(bias);
          const double y = got[static_cast<std::size_t>(m * c.N + n)];
          const double y32 = f32[static_cast<std::size_t>(m * c.N + n)];
          if (!(std::abs(y - emulated) <= (double(c.K) + 8) * 0x1p-24 * (scale * (1 + 0x1p-8)) + 1e-30)) ++outside_emulation;
          if (!(std::abs(y - exact) <= eps * scale + 1e-30)) ++outside_bound;
          if (!(std::abs(y - y32) <= (eps + (double(c.K) + 8) * 0x1p-24) * scale + 1e-30)) ++outside_vs_f32;
          if (sq > 0) {
            sq_err += (y - exact) * (y - exact) / sq;
            sq_norm += 1;
          }
        }
      CAPTURE(cpu::isa_name(bf16_path));
      CAPTURE(c.M);
      CAPTURE(c.N);
      CAPTURE(c.K);
      CAPTURE(threads);
      CHECK(outside_emulation == 0);
      CHECK(outside_bound == 0);
      CHECK(outside_vs_f32 == 0);
      const double rms = std::sqrt(sq_err / sq_norm), typical = 0x1p-8 / std::sqrt(3.0);
      CAPTURE(rms);
      if (c.K >= 64 && c.M * c.N >= 1000) {  // enough terms and elements for a stable RMS
        CHECK(rms <= 1.1 * typical);
        CHECK(rms >= 0.2 * typical);
      }
    }
}

TEST_CASE("bf16 weights without AVX512-BF16: widened, float32 arithmetic") {
  // The same products on the widening path are float32-accurate (the bound above without 2^-8).
  const cpu::Isa widen = std::min(cpu::cpu_features().best(), cpu::Isa::Avx512,
                                  [](cpu::Isa a, cpu::Isa b) { return static_cast<int>(a) < static_cast<int>(b); });
  const Case c{131, 257, 1024};
  const Data d = make(c, 5);
  const auto got = run(widen, c, d, 2);
  double worst = 0;
  for (std::int64_t m = 0; m < c.M; ++m)
    for (std::int64_t n = 0; n < c.N; ++n) {
      double exact = double(float(bf16(d.b[n]))), mag = std::abs(exact);
      for (std::int64_t k = 0; k < c.K; ++k) {
        const double p = double(d.x[m * c.K + k]) * double(float(d.w[n * c.K + k]));
        exact += p;
        mag += std::abs(p);
      }
      worst = std::max(worst, std::abs(got[static_cast<std::size_t>(m * c.N + n)] - exact) / mag);
    }
  CAPTURE(cpu::isa_name(widen));
  CHECK(worst <= (double(c.K) + 8) * 0x1p-24);
}
