// Tests for epona/cpu/gemm.hpp: linear = act(x·Wᵀ + b) with float32 and bfloat16 weights
// (widened to float32; the BF16 dot-product path is gemm_bf16.cpp's),
// with and without bias, each epilogue, odd sizes (and N across the bf16 widening blocks),
// the strided pointer form, and shape errors. Reference: float64 loop over the same (widened)
// weights. Tolerance: max |got − ref| / max |ref| <= 1e-5.
#include <doctest/doctest.h>

#include <cmath>

#include "epona/core/error.hpp"
#include "epona/cpu/gemm.hpp"
#include "testing.hpp"

using namespace epona;
using cpu::Epilogue;
using cpu::HostTensor;

namespace {
double activate(double x, Epilogue e) {
  switch (e) {
    case Epilogue::None: return x;
    case Epilogue::GeluErf: return 0.5 * x * (1.0 + std::erf(x / std::sqrt(2.0)));
    case Epilogue::GeluTanh: return 0.5 * x * (1.0 + std::tanh(std::sqrt(2.0 / M_PI) * (x + 0.044715 * x * x * x)));
    case Epilogue::Silu: return x / (1.0 + std::exp(-x));
  }
  return x;
}

template <class W>
std::vector<double> linear_ref(const std::vector<float>& x, const HostTensor<W>& w, const HostTensor<W>& b,
                               std::int64_t M, Epilogue e) {
  const std::int64_t N = w.size(0), K = w.size(1);
  std::vector<double> y(static_cast<std::size_t>(M * N));
  for (std::int64_t m = 0; m < M; ++m)
    for (std::int64_t n = 0; n < N; ++n) {
      double acc = b.empty() ? 0.0 : double(float(b.data()[n]));
      for (std::int64_t k = 0; k < K; ++k) acc += double(x[m * K + k]) * double(float(w.data()[n * K + k]));
      y[m * N + n] = activate(acc, e);
    }
  return y;
}

template <class W>
HostTensor<W> random_tensor(Shape shape, std::uint32_t seed, float amp) {
  HostTensor<W> t(shape);
  const auto v = test::random_floats(static_cast<std::size_t>(t.numel()), seed, -amp, amp);
  for (std::size_t i = 0; i < v.size(); ++i) t.data()[i] = W(v[i]);
  return t;
}

template <class W>
void check_linear(std::int64_t M, std::int64_t N, std::int64_t K) {
  cpu::Context ctx;
  const float amp = 2.0f / std::sqrt(static_cast<float>(K));  // outputs O(1): the activations' interesting range
  auto x = HostTensor<float>({M, K});
  const auto xv = test::random_floats(static_cast<std::size_t>(M * K), 5 + static_cast<std::uint32_t>(K), -1.f, 1.f);
  std::copy(xv.begin(), xv.end(), x.data());
  const auto w = random_tensor<W>({N, K}, 6 + static_cast<std::uint32_t>(N), amp);
  const auto b = random_tensor<W>({N}, 8, 1.f);
  for (bool with_bias : {false, true})
    for (auto e : {Epilogue::None, Epilogue::GeluErf, Epilogue::GeluTanh, Epilogue::Silu}) {
      const HostTensor<W> bias = with_bias ? b : HostTensor<W>();
      HostTensor<float> y({M, N});
      cpu::linear(ctx, x, w, bias, y, e);
      CAPTURE(M);
      CAPTURE(N);
      CAPTURE(K);
      CAPTURE(with_bias);
      CAPTURE(static_cast<int>(e));
      CHECK(test::rel_max(y.data(), linear_ref(xv, w, bias, M, e).data(), static_cast<std::size_t>(M * N)) <=
            1e-5);
    }
}
}  // namespace

TEST_CASE("linear with float32 weights, every epilogue, with and without bias") {
  // Up to 4 rows go through dot products, more through the best micro-kernel family of this
  // CPU (K odd and K not a multiple of the SIMD width included); gemm_isa.cpp forces each one.
  for (auto [M, N, K] : {std::tuple<std::int64_t, std::int64_t, std::int64_t>{1, 1, 1}, {7, 13, 5}, {33, 17, 65},
                         {100, 300, 129}, {257, 31, 260},
                         {3, 1001, 300},   // few rows: dot products over weight rows
                         {1, 300, 2048}, {4, 70, 33}, {6, 500, 300}})  // 6 rows: column blocks
    check_linear<float>(M, N, K);
}

TEST_CASE("linear with bfloat16 weights widened to float32 (every path but the BF16 dot products)") {
  // The AVX512-BF16 kernels round the activations to bf16 as well: their tolerance is stated
  // and tested in gemm_bf16.cpp. Here the best kernel family below them, whose error is fp32's.
  const cpu::Isa below_bf16 = std::min(cpu::cpu_features().best(), cpu::Isa::Avx512,
                                       [](cpu::Isa a, cpu::Isa b) { return static_cast<int>(a) < static_cast<int>(b); });
  cpu::ScopedIsa isa(below_bf16);
  for (auto [M, N, K] : {std::tuple<std::int64_t, std::int64_t, std::int64_t>{1, 1, 1}, {7, 13, 5}, {41, 600, 77},
                         {130, 257, 200}, {2, 1500, 200},
                         {1, 300, 2048}, {4, 70, 33}, {3, 41, 95}, {6, 500, 300}})
    check_linear<bf16>(M, N, K);
}

TEST_CASE("linear pointer form with row strides writes a column block of a wider output") {
  cpu::Context ctx;
  const std::int64_t M = 23, N = 37, K = 45, ldx = K + 3, ldy = N + 9, off = 4;
  const auto x = test::random_floats(static_cast<std::size_t>(M * ldx), 91);
  const auto w = test::random_floats(static_cast<std::size_t>(N * K), 92, -0.3f, 0.3f);
  const auto b = test::random_floats(static_cast<std::size_t>(N), 93);
  std::vector<float> y(static_cast<std::size_t>(M * ldy), -9.f);
  cpu::linear<float>(ctx, x.data(), ldx, w.data(), b.data(), y.data() + off, ldy, M, N, K, Epilogue::GeluTanh);
  std::vector<float> got;
  std::vector<double> ref;
  for (std::int64_t m = 0; m < M; ++m)
    for (std::int64_t c = 0; c < ldy; ++c) {
      if (c < off || c >= off + N) {
        CHECK(y[m * ldy + c] == -9.f);
        continue;
      }
      const std::int64_t n = c - off;
      double acc = b[n];
      for (std::int64_t k = 0; k < K; ++k) acc += double(x[m * ldx + k]) * w[n * K + k];
      got.push_back(y[m * ldy + c]);
      ref.push_back(activate(acc, Epilogue::GeluTanh));
    }
  CHECK(test::rel_max(got, ref) <= 1e-5);
}

TEST_CASE("linear rejects mismatched shapes with a message") {
  cpu::Context ctx;
  HostTensor<float> x({4, 8}), w({5, 8}), bad_w({5, 7}), b({6}), y({4, 5}), bad_y({4, 6});
  CHECK_THROWS_WITH_AS(cpu::linear(ctx, x, bad_w, HostTensor<float>(), y), doctest::Contains("does not end in K"), Error);
  CHECK_THROWS_WITH_AS(cpu::linear(ctx, x, w, HostTensor<float>(), bad_y), doctest::Contains("output"), Error);
  CHECK_THROWS_WITH_AS(cpu::linear(ctx, x, w, b, y), doctest::Contains("bias"), Error);
  CHECK_THROWS_WITH_AS(cpu::linear(ctx, x, HostTensor<float>({5, 8, 1}), HostTensor<float>(), y),
                       doctest::Contains("2-d"), Error);
}
