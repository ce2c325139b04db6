// Our kernels for linear layers cuBLASLt's tiles fit badly (small_linear.cuh, skinny_linear.cuh)
// against a float64 host product of the same (rounded) inputs: a few outputs per row (warp per
// output; K a multiple of 8 or not), a tiny K (thread per output), and at most 16 rows (the
// skinny-M kernel, called directly and through cuda::linear, which takes it only where it beats
// cuBLASLt: the TrajDiT's 15 trajectory rows at its real widths, 1, 2 and 16 rows, 3 outputs,
// bias or none, no activation or the tanh GELU). x is a column block of a wider
// buffer (ldx > K) and y is written into a column block of a wider poisoned buffer, whose
// other columns must stay poisoned. Bound per element: float32 1e-5 of max|ref|; bf16 one
// rounding of the output (2^-8 |ref|) on top for our kernels; through cuda::linear also one of
// the product before cuBLASLt's bias / GELU epilogue (see check_product).
#include <doctest/doctest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cuda_test_util.cuh"
#include "epona/cuda/backend.cuh"

using namespace epona;

namespace {

cuda::Context& gpu() {
  static cuda::Context ctx;
  return ctx;
}

struct Product {
  std::int64_t M, N, K;
  bool bias = true;
  Epilogue epi = Epilogue::None;
};

enum class Route { Linear, Skinny };  // through cuda::linear, or the skinny kernel called directly

double gelu_tanh(double v) { return 0.5 * v * (1.0 + std::tanh(0.7978845608028654 * (v + 0.044715 * v * v * v))); }

// x occupies columns [x_col, x_col + K) of rows ldx wide, y columns [y_col, y_col + N) of
// rows ldy wide (x_col keeps 16-byte alignment: the skinny kernel needs aligned rows).
template <class T>
void check_product(const Product& p, Route route, std::uint32_t seed) {
  auto& ctx = gpu();
  const std::int64_t x_col = 32, ldx = p.K + 64, y_col = 3, ldy = p.N + 8;
  auto x = test::random_tensor({p.M, ldx}, seed, -2.f, 2.f), w = test::random_tensor({p.N, p.K}, seed + 1, -0.5f, 0.5f);
  auto b = test::random_tensor({p.N}, seed + 2);
  test::round_to<T>(x), test::round_to<T>(w), test::round_to<T>(b);
  const auto dx = test::upload<T>(ctx, x), dw = test::upload<T>(ctx, w), db = test::upload<T>(ctx, b);
  auto dy = test::Dev<T>({p.M, ldy});
  test::poison(ctx, dy);
  const T* bias = p.bias ? db.data() : nullptr;
  if (route == Route::Linear) {
    cuda::linear(ctx, dx.data() + x_col, ldx, dw.data(), bias, dy.data() + y_col, ldy, p.M, p.N, p.K, p.epi);
  } else {
    const cuda::detail::LinearArgs<T> a{dx.data() + x_col, ldx, dw.data(), bias, dy.data() + y_col, ldy,
                                        static_cast<int>(p.M), static_cast<int>(p.N), static_cast<int>(p.K)};
    REQUIRE(cuda::detail::skinny_linear(ctx, a, p.epi));
  }
  const auto y = test::download(ctx, dy);
  double max_ref = 0;
  std::vector<double> ref(static_cast<std::size_t>(p.M * p.N)), slack(ref.size());
  // bf16: our kernels round once, the output. Through cuda::linear the product may go to
  // cuBLASLt, whose bias / GELU epilogue on these small-M shapes can also round x·w before the
  // bias and the activation (seen on the H200: up to 1.4 roundings of max|ref|), so there each
  // element may be off by 2^-8 (1.13 (|x·w| + |x·w + b|) + |ref|), 1.13 bounding GELU's slope.
  for (std::int64_t m = 0; m < p.M; ++m)
    for (std::int64_t n = 0; n < p.N; ++n) {
      double xw = 0;
      for (std::int64_t k = 0; k < p.K; ++k) xw += double(x.at(m, x_col + k)) * double(w.at(n, k));
      const double z = xw + (p.bias ? b.data()[n] : 0.0), r = p.epi == Epilogue::GeluTanh ? gelu_tanh(z) : z;
      ref[m * p.N + n] = r;
      slack[m * p.N + n] = route == Route::Linear ? 1.13 * (std::abs(xw) + std::abs(z)) + std::abs(r) : std::abs(r);
      max_ref = std::max(max_ref, std::abs(r));
    }
  const double u = std::is_same_v<T, bf16> ? 1.0 / 256 : 0.0;
  int bad = 0, untouched_changed = 0;
  double worst = 0;
  for (std::int64_t m = 0; m < p.M; ++m)
    for (std::int64_t c = 0; c < ldy; ++c) {
      const float got = y.at(m, c);
      if (c < y_col || c >= y_col + p.N) {
        untouched_changed += !std::isnan(got);
        continue;
      }
      const double r = ref[m * p.N + c - y_col], err = std::abs(double(got) - r);
      worst = std::max(worst, err / max_ref);
      bad += !(err <= u * slack[m * p.N + c - y_col] + 1e-5 * max_ref);
    }
  const std::string via = route == Route::Linear ? "linear " : "skinny ";
  MESSAGE((via + test::type_name<T>()), " ", p.M, "x", p.N, "x", p.K,
          (std::string(p.bias ? " +bias" : "") + (p.epi == Epilogue::GeluTanh ? " gelu" : "")), ": max err ", worst, " of max|ref|");
  CHECK(bad == 0);
  CHECK(untouched_changed == 0);
}

// The skinny kernel needs thread-block clusters: a GPU of compute capability 9.0 or newer
// running code built for one (elsewhere cuda::linear never takes it).
bool skinny_here() {
  const bool here = cuda::detail::clusters_available(gpu());
  if (!here) MESSAGE("no thread-block clusters on this GPU / in this build: skinny kernel not checked directly");
  return here;
}

template <class T>
void check_both_routes(const Product& p, std::uint32_t seed) {
  if (skinny_here()) check_product<T>(p, Route::Skinny, seed);
  check_product<T>(p, Route::Linear, seed + 7);
}

}  // namespace

TEST_CASE("linear: few outputs per row and tiny K run in the small kernels, exact to float64 within rounding") {
  EPONA_REQUIRE_GPU();
  std::uint32_t seed = 600;
  for (const bool bias : {true, false}) {
    check_product<float>({15, 3, 1024, bias}, Route::Linear, seed++);  // the TrajDiT's final layer
    check_product<bf16>({15, 3, 1024, bias}, Route::Linear, seed++);
    check_product<bf16>({15, 1024, 3, bias}, Route::Linear, seed++);  // its input layer
    check_product<float>({15, 1024, 3, bias}, Route::Linear, seed++);
    check_product<bf16>({37, 16, 1027, bias}, Route::Linear, seed++);  // K not a multiple of 8: element loads
    check_product<bf16>({5, 7, 16, bias}, Route::Linear, seed++);      // largest tiny K
  }
}

TEST_CASE_TEMPLATE("linear: at most 16 rows run in the skinny kernel, exact to float64 within rounding", T, bf16, float) {
  EPONA_REQUIRE_GPU();
  std::uint32_t seed = 700;
  const Epilogue gelu = Epilogue::GeluTanh;
  // The TrajDiT's trajectory-stream products (D 1024, MLP 4096): qkv, proj, fc1 (GELU), fc2,
  // the single block's linear2 (K = D + MLP).
  for (const Product& p : {Product{15, 3072, 1024}, Product{15, 1024, 1024}, Product{15, 4096, 1024, true, gelu},
                           Product{15, 1024, 4096}, Product{15, 1024, 5120}})
    check_both_routes<T>(p, seed += 10);
  // Other row counts, no bias, the GELU without bias, few outputs (a partial band), K = 4096.
  for (const Product& p : {Product{1, 1024, 1024, false}, Product{2, 3072, 5120, true, gelu}, Product{16, 4096, 4096},
                           Product{16, 1024, 5120, false, gelu}, Product{1, 4096, 1024, true, gelu},
                           Product{2, 3, 1024}, Product{16, 3, 5120, true, gelu}, Product{15, 1000, 1024, false}})
    check_both_routes<T>(p, seed += 10);
}

TEST_CASE("skinny linear declines what it cannot run (the caller falls back to cuBLASLt)") {
  EPONA_REQUIRE_GPU();
  auto& ctx = gpu();
  test::Dev<bf16> x({17, 1032}), w({64, 1032}), y({17, 64});
  cuda::fill_bytes(ctx, x, 0), cuda::fill_bytes(ctx, w, 0);
  const auto args = [&](int M, int K, std::int64_t ldx, const bf16* xp) {
    return cuda::detail::LinearArgs<bf16>{xp, ldx, w.data(), nullptr, y.data(), 64, M, 64, K};
  };
  CHECK_FALSE(cuda::detail::skinny_linear(ctx, args(17, 1024, 1032, x.data()), Epilogue::None));  // 17 rows
  CHECK_FALSE(cuda::detail::skinny_linear(ctx, args(15, 1020, 1032, x.data()), Epilogue::None));  // K % 8
  CHECK_FALSE(cuda::detail::skinny_linear(ctx, args(15, 1024, 1030, x.data()), Epilogue::None));  // row stride
  CHECK_FALSE(cuda::detail::skinny_linear(ctx, args(15, 1024, 1032, x.data() + 1), Epilogue::None));  // alignment
  CHECK_FALSE(cuda::detail::skinny_linear(ctx, args(15, 1024, 1032, x.data()), Epilogue::GeluErf));
  CHECK_FALSE(cuda::detail::skinny_linear(ctx, args(15, 1024, 1032, x.data()), Epilogue::Silu));
  CHECK(cuda::detail::skinny_linear(ctx, args(15, 1024, 1032, x.data()), Epilogue::None) == skinny_here());
  ctx.synchronize();
}
