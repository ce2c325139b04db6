// GPU tests for the bf16 lookup-table path of epona/cuda/activation.cuh (GELU erf, GELU tanh,
// SiLU): the table path must give the same bits as computing the function (every one of the
// 2^16 bf16 inputs, NaN and infinities included), match a float64 reference within one bf16
// rounding, write every element (poisoned output), handle a ragged tail of packs, and fall
// back without creating a table while a stream is being captured into a graph.
#include "cuda_test_util.cuh"

#include <cstring>

using namespace epona;
using namespace epona::test;

namespace {

constexpr std::int64_t kLarge = cuda::detail::kTableMinElements + 8 * 37;  // a ragged last stride

// Every bf16 bit pattern, repeated to `n` elements (so the table path is taken).
Tensor<bf16, Cpu> all_patterns(std::int64_t n) {
  Tensor<bf16, Cpu> t({n});
  for (std::int64_t i = 0; i < n; ++i) t.data()[i].bits = static_cast<std::uint16_t>(i * 40503u + (i >> 16));
  for (std::int64_t i = 0; i < cuda::detail::kBf16Values; ++i) t.data()[i].bits = static_cast<std::uint16_t>(i);
  return t;
}

std::vector<std::uint16_t> bits_of(cuda::Context& ctx, const Dev<bf16>& d) {
  const auto h = cuda::to_host(ctx, d);
  std::vector<std::uint16_t> b(h.numel());
  for (std::int64_t i = 0; i < h.numel(); ++i) b[i] = h.data()[i].bits;
  return b;
}

// The table path (x -> poisoned y) against the direct kernel, bit for bit.
template <class Op>
void check_bit_identical(cuda::Context& ctx, Op op) {
  const char* name = Op::table;
  const auto host = all_patterns(kLarge);
  const auto x = cuda::to_device(ctx, host);
  Dev<bf16> direct({kLarge}), table({kLarge});
  poison(ctx, direct), poison(ctx, table);
  cuda::detail::map(ctx, x.data(), direct.data(), kLarge, op);
  cuda::detail::map_bf16(ctx, x.data(), table.data(), kLarge, op);
  CHECK_MESSAGE(ctx.has_constant_table(name), name, ": the table path was not taken");
  const auto a = bits_of(ctx, direct), b = bits_of(ctx, table);
  std::int64_t differ = 0;
  for (std::int64_t i = 0; i < kLarge; ++i) differ += a[i] != b[i];
  CHECK_MESSAGE(differ == 0, name, ": ", differ, " of ", kLarge, " elements differ from the direct kernel");
}

// In place through the public function, against float64 math: within one bf16 rounding of
// the reference (plus float32's own error, far below it).
template <class F64>
void check_against_f64(cuda::Context& ctx, const char* name, void (*gpu)(cuda::Context&, bf16*, std::int64_t), F64 ref) {
  HostF x = random_tensor({kLarge}, 7, -8.f, 8.f);
  round_to<bf16>(x);
  auto d = upload<bf16>(ctx, x);
  gpu(ctx, d.data(), kLarge);
  const HostF out = download(ctx, d);
  double worst = 0;
  for (std::int64_t i = 0; i < kLarge; ++i) {
    const double r = ref(static_cast<double>(x.data()[i]));
    worst = std::max(worst, std::abs(out.data()[i] - r) / std::max(std::abs(r), 1e-30));
  }
  MESSAGE(name, " bf16 table path: max relative error ", worst, " (bound 2^-8)");
  CHECK(worst <= 1.0 / 256);
}

}  // namespace

TEST_CASE("bf16 activation tables give the direct kernel's bits for every input") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_bit_identical(ctx, cuda::detail::GeluErfOp{});
  check_bit_identical(ctx, cuda::detail::GeluTanhOp{});
  check_bit_identical(ctx, cuda::detail::SiluOp{});
}

TEST_CASE("bf16 activation tables against float64") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_against_f64(ctx, "gelu_erf", cuda::gelu_erf<bf16>, [](double v) { return 0.5 * v * (1 + std::erf(v / std::sqrt(2.0))); });
  check_against_f64(ctx, "gelu_tanh", cuda::gelu_tanh<bf16>, [](double v) {
    return 0.5 * v * (1 + std::tanh(std::sqrt(2 / M_PI) * (v + 0.044715 * v * v * v)));
  });
  check_against_f64(ctx, "silu", cuda::silu<bf16>, [](double v) { return v / (1 + std::exp(-v)); });
}

TEST_CASE("bf16 activation tables are not created inside a graph capture") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const auto host = all_patterns(kLarge);
  auto x = cuda::to_device(ctx, host);
  Dev<bf16> expect({kLarge});
  cuda::detail::map(ctx, x.data(), expect.data(), kLarge, cuda::detail::GeluErfOp{});
  cudaGraph_t graph = nullptr;
  EPONA_CUDA_CHECK(cudaStreamBeginCapture(ctx.stream(), cudaStreamCaptureModeRelaxed));
  cuda::gelu_erf(ctx, x.data(), kLarge);
  EPONA_CUDA_CHECK(cudaStreamEndCapture(ctx.stream(), &graph));
  CHECK_FALSE(ctx.has_constant_table("gelu_erf_bf16"));
  cudaGraphExec_t exec = nullptr;
  EPONA_CUDA_CHECK(cudaGraphInstantiate(&exec, graph, 0));
  EPONA_CUDA_CHECK(cudaGraphLaunch(exec, ctx.stream()));
  ctx.synchronize();
  CHECK(bits_of(ctx, x) == bits_of(ctx, expect));
  // Outside a capture the table is built, and a graph captured afterwards uses it.
  x = cuda::to_device(ctx, host);
  cuda::gelu_erf(ctx, x.data(), kLarge);
  CHECK(ctx.has_constant_table("gelu_erf_bf16"));
  CHECK(bits_of(ctx, x) == bits_of(ctx, expect));
  cudaGraphExecDestroy(exec);
  cudaGraphDestroy(graph);
}

TEST_CASE("small, misaligned or float32 maps keep the direct kernel") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  HostF x = random_tensor({4096}, 3, -4.f, 4.f);
  round_to<bf16>(x);
  auto d = upload<bf16>(ctx, x);
  cuda::gelu_erf(ctx, d.data(), x.numel());
  CHECK_FALSE(ctx.has_constant_table("gelu_erf_bf16"));
  auto f = upload<float>(ctx, random_tensor({kLarge}, 4));
  cuda::silu(ctx, f.data(), kLarge);
  CHECK_FALSE(ctx.has_constant_table("silu_bf16"));
}

TEST_CASE("linear's erf-GELU and SiLU epilogues take the table on large bf16 outputs, same bits") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const std::int64_t M = 515, N = 8192, K = 64;  // an MST fc1 shape at a small K
  HostF x = random_tensor({M, K}, 11, -2.f, 2.f), w = random_tensor({N, K}, 12, -0.3f, 0.3f),
        b = random_tensor({N}, 13);
  const auto dx = upload<bf16>(ctx, x), dw = upload<bf16>(ctx, w), db = upload<bf16>(ctx, b);
  auto check = [&](cuda::Epilogue epi, auto op) {
    Dev<bf16> fused({M, N}), plain({M, N});
    poison(ctx, fused), poison(ctx, plain);
    cuda::linear(ctx, dx, dw, db, fused, epi);
    cuda::linear(ctx, dx, dw, db, plain, cuda::Epilogue::None);
    cuda::detail::map(ctx, plain.data(), plain.data(), M * N, op);
    CHECK(ctx.has_constant_table(decltype(op)::table));
    CHECK(bits_of(ctx, fused) == bits_of(ctx, plain));
  };
  check(cuda::Epilogue::GeluErf, cuda::detail::GeluErfOp{});
  check(cuda::Epilogue::Silu, cuda::detail::SiluOp{});
}
