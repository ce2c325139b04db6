// GPU tests for epona/cuda/gemm/gemm.cuh: linear() with every epilogue, with and without bias,
// float32 and bf16, odd and model-like sizes, misaligned operands, against cpu::linear on the
// same (bf16-rounded) inputs. float32 within 1e-5 (TF32 must be off). bf16: the product
// rounded once (2^-8 of each value); with an activation, the pre-activation z may be rounded
// too (PyTorch rounds the Linear's output before the activation; cuBLASLt's fused GELU is
// not documented either way), so |err| <= 2^-8 (1.13 |z| + |act(z)|), 1.13 bounding the
// slope of GELU and SiLU.
#include "cuda_test_util.cuh"

#include <algorithm>
#include <atomic>
#include <limits>

using namespace epona;
using namespace epona::test;

namespace {

// See the header comment; z is the pre-activation (x wᵀ + b), ref the result.
template <class T>
Bound linear_bound(cuda::Epilogue epi, const HostF& z, const HostF& ref) {
  if (std::is_same_v<T, float> || epi == cuda::Epilogue::None) return one_rounding<T>(max_abs(ref));
  constexpr double u = kBf16Roundoff, slope = 1.13;
  return {u * (slope * norm2(z) / norm2(ref) + 1) + kF32Tol, u * (slope * max_abs(z) + max_abs(ref)) + kF32Tol * max_abs(ref)};
}

struct Case {
  std::int64_t M, N, K;
  bool bias;
  cuda::Epilogue epi;
  std::int64_t misalign = 0;  // elements: shifts x, w, bias and y off their 256-byte alignment
};

template <class T>
void check_linear(cuda::Context& ctx, const Case& c, std::uint32_t seed) {
  cpu::Context cctx;
  HostF x = random_tensor({c.M, c.K}, seed);
  HostF w = random_tensor({c.N, c.K}, seed + 1, -1.f / std::sqrt(float(c.K)), 1.f / std::sqrt(float(c.K)));
  HostF b = c.bias ? random_tensor({c.N}, seed + 2) : HostF();
  round_to<T>(x), round_to<T>(w);
  if (c.bias) round_to<T>(b);
  HostF ref({c.M, c.N});
  cpu::linear(cctx, x, w, b, ref, c.epi);

  auto dx = upload<T>(ctx, x, c.misalign), dw = upload<T>(ctx, w, c.misalign);
  auto db = c.bias ? upload<T>(ctx, b, c.misalign) : Dev<T>();
  auto dy = upload<T>(ctx, ref, c.misalign);
  poison(ctx, dy);
  cuda::linear(ctx, dx, dw, db, dy, c.epi);
  const HostF out = download(ctx, dy);

  const std::string what = std::string("linear ") + type_name<T>() + " M=" + std::to_string(c.M) + " N=" +
                           std::to_string(c.N) + " K=" + std::to_string(c.K) + (c.bias ? " +bias " : " ") +
                           epilogue_name(c.epi) + (c.misalign ? " misaligned" : "");
  HostF z({c.M, c.N});
  cpu::linear(cctx, x, w, b, z, cpu::Epilogue::None);
  check_error(measure(out, ref), linear_bound<T>(c.epi, z, ref), what);
}

template <class T>
void check_all_epilogues(cuda::Context& ctx, std::int64_t M, std::int64_t N, std::int64_t K, std::uint32_t seed,
                         std::int64_t misalign = 0) {
  for (auto epi : {cuda::Epilogue::None, cuda::Epilogue::GeluErf, cuda::Epilogue::GeluTanh, cuda::Epilogue::Silu})
    for (bool bias : {false, true}) check_linear<T>(ctx, {M, N, K, bias, epi, misalign}, seed++);
}

// Columns col0 .. col0 + N of rows ldy wide, as a predicate on flat indices.
struct ColumnBlock {
  std::int64_t ldy, col0, N;
  bool operator()(std::int64_t i) const { return i % ldy >= col0 && i % ldy < col0 + N; }
};

// Elements of a NaN-poisoned buffer outside `block` that were written (are no longer NaN).
std::int64_t written_outside(const HostF& out, const ColumnBlock& block) {
  std::int64_t touched = 0;
  for (std::int64_t i = 0; i < out.numel(); ++i) touched += !block(i) && !std::isnan(out.data()[i]);
  return touched;
}

// out: a (M, ldy) buffer, poisoned, into whose columns col0 .. col0 + N the product of xw (rows
// ldx apart), w and bias was written. Checks that block against cpu::linear on the same
// (rounded) operands within the linear bound, and that no other element was written.
template <class T>
void check_column_block(const HostF& out, const HostF& xw, std::int64_t ldx, const HostF& w, const float* bias,
                        std::int64_t M, std::int64_t N, std::int64_t K, std::int64_t ldy, std::int64_t col0,
                        cuda::Epilogue epi, const std::string& what) {
  cpu::Context cctx;
  HostF ref({M, ldy}), z({M, N}), y({M, N});  // z, y: the same product densely, for the bound
  std::fill_n(ref.data(), ref.numel(), std::numeric_limits<float>::quiet_NaN());
  cpu::linear(cctx, xw.data(), ldx, w.data(), bias, ref.data() + col0, ldy, M, N, K, epi);
  cpu::linear(cctx, xw.data(), ldx, w.data(), bias, z.data(), N, M, N, K, cpu::Epilogue::None);
  cpu::linear(cctx, xw.data(), ldx, w.data(), bias, y.data(), N, M, N, K, epi);
  const ColumnBlock inside{ldy, col0, N};
  check_error(measure(out.data(), ref.data(), out.numel(), inside), linear_bound<T>(epi, z, y), what);
  CHECK(written_outside(out, inside) == 0);
}

}  // namespace

TEST_CASE_TEMPLATE("cuda linear matches cpu::linear on odd and small sizes", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_all_epilogues<T>(ctx, 1, 1, 1, 100);
  check_all_epilogues<T>(ctx, 3, 5, 7, 200);
  check_all_epilogues<T>(ctx, 37, 53, 29, 300);
  check_all_epilogues<T>(ctx, 130, 257, 200, 400);
}

TEST_CASE_TEMPLATE("cuda linear with misaligned operands (bias added outside cuBLASLt)", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_all_epilogues<T>(ctx, 33, 96, 64, 500, /*misalign=*/1);
  check_all_epilogues<T>(ctx, 16, 40, 24, 600, /*misalign=*/3);
}

TEST_CASE_TEMPLATE("cuda linear at model-like sizes", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_linear<T>(ctx, {530, 3072, 1024, true, cuda::Epilogue::GeluTanh}, 700);  // TrajDiT linear1-like
  check_linear<T>(ctx, {515, 2048, 2048, true, cuda::Epilogue::None}, 701);      // cond_in
  check_linear<T>(ctx, {257, 8192, 2048, true, cuda::Epilogue::GeluErf}, 702);   // MST c_fc (fewer rows)
  // Plans are cached per shape: a second call with other data must still be right.
  check_linear<T>(ctx, {530, 3072, 1024, true, cuda::Epilogue::GeluTanh}, 703);
}

namespace {

// The context's cached plans of M rows, tuned (timed candidates) or not.
std::size_t plans_of(cuda::Context& ctx, std::int64_t M, bool tuned) {
  std::size_t n = 0;
  for (const auto& [key, plan] : ctx.gemm_plans())
    n += key[1] == M && ((key[6] & cuda::detail::kUntunedPlan) == 0) == tuned;
  return n;
}


}  // namespace

// Timed candidates (the default for products of >= kTuneRowsMin rows, every product with
// EPONA_CUDA_GEMM_TUNE=1): whichever wins, the result is within the same bound, and the plan
// cache shows which products were timed.
TEST_CASE_TEMPLATE("cuda linear with cuBLASLt's candidates timed matches cpu::linear", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  const std::int64_t large = cuda::detail::kTuneRowsMin + 5;
  {
    cuda::Context ctx;
    ctx.policy().gemm_tuning = cuda::GemmTuning::Large;
    check_linear<T>(ctx, {large, 96, 64, true, cuda::Epilogue::GeluErf}, 800);
    check_linear<T>(ctx, {37, 96, 64, true, cuda::Epilogue::None}, 801);
    CHECK(plans_of(ctx, large, true) == 1);
    CHECK(plans_of(ctx, 37, false) == 1);
    check_linear<T>(ctx, {large, 96, 64, true, cuda::Epilogue::GeluErf}, 802);  // the cached tuned plan again
  }
  {
    cuda::Context ctx;
    ctx.policy().gemm_tuning = cuda::GemmTuning::All;
    check_linear<T>(ctx, {37, 96, 64, true, cuda::Epilogue::GeluTanh}, 803);
    CHECK(plans_of(ctx, 37, true) == 1);
  }
  {
    cuda::Context ctx;
    ctx.policy().gemm_tuning = cuda::GemmTuning::Off;
    check_linear<T>(ctx, {large, 96, 64, false, cuda::Epilogue::None}, 804);
    CHECK(plans_of(ctx, large, false) == 1);
  }
}

// y as a column block of a wider buffer and x read with a row stride (the pointer form):
// exactly the block is written, the other columns keep their poison.
TEST_CASE_TEMPLATE("cuda linear with row strides writes only its column block", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const std::int64_t M = 45, N = 72, K = 40, ldx = 56, col0 = 16;
  // ldy 100: element-wise epilogue pass one element at a time; 104: in 16-byte packs.
  for (std::int64_t ldy : {100, 104})
  for (auto epi : {cuda::Epilogue::None, cuda::Epilogue::GeluErf, cuda::Epilogue::GeluTanh}) {
    HostF xw = random_tensor({M, ldx}, 800), w = random_tensor({N, K}, 801, -0.2f, 0.2f), b = random_tensor({N}, 802);
    round_to<T>(xw), round_to<T>(w), round_to<T>(b);
    auto dx = upload<T>(ctx, xw), dw = upload<T>(ctx, w), db = upload<T>(ctx, b);
    Dev<T> dy({M, ldy});
    poison(ctx, dy);
    cuda::linear(ctx, dx.data(), ldx, dw.data(), db.data(), dy.data() + col0, ldy, M, N, K, epi);
    check_column_block<T>(download(ctx, dy), xw, ldx, w, b.data(), M, N, K, ldy, col0, epi,
                          std::string("linear strided ") + type_name<T>() + " ldy " + std::to_string(ldy) + " " +
                              epilogue_name(epi));
  }
}

// linear_accumulate: y (float32) += x wᵀ, y a column block of a wider NaN-filled buffer, x read
// with a row stride. The sum is not rounded to T on the way: within float32 accumulation error
// of the float32 reference y0 + cpu::linear, far inside one bf16 rounding.
// With every product's candidates timed (All), the timing runs go to a scratch buffer: y gets
// the product added once.
TEST_CASE_TEMPLATE("cuda linear_accumulate adds the unrounded product to float32 y, only in its block", T, float,
                   bf16) {
  EPONA_REQUIRE_GPU();
  cpu::Context cctx;
  struct Shape { std::int64_t M, N, K, ldx, ldy, col0; };
  for (const auto tuning : {cuda::GemmTuning::Off, cuda::GemmTuning::All}) {
    for (const Shape& c : {Shape{45, 72, 40, 56, 100, 16}, Shape{515, 2048, 2048, 2048, 2048, 0}}) {
      cuda::Context ctx;  // a fresh plan cache: the plan is made (and timed) here
      ctx.policy().gemm_tuning = tuning;
      HostF xw = random_tensor({c.M, c.ldx}, 900), w = random_tensor({c.N, c.K}, 901, -0.05f, 0.05f);
      round_to<T>(xw), round_to<T>(w);
      const HostF y0 = random_tensor({c.M, c.N}, 902, -4.f, 4.f);
      HostF start({c.M, c.ldy}), ref;
      std::fill_n(start.data(), start.numel(), std::numeric_limits<float>::quiet_NaN());
      for (std::int64_t r = 0; r < c.M; ++r)
        for (std::int64_t j = 0; j < c.N; ++j) start.at(r, c.col0 + j) = y0.at(r, j);
      ref = start.clone();
      HostF product({c.M, c.N});
      cpu::linear(cctx, xw.data(), c.ldx, w.data(), static_cast<const float*>(nullptr), product.data(), c.N, c.M, c.N,
                  c.K, cpu::Epilogue::None);
      for (std::int64_t r = 0; r < c.M; ++r)
        for (std::int64_t j = 0; j < c.N; ++j) ref.at(r, c.col0 + j) += product.at(r, j);
      auto dx = upload<T>(ctx, xw), dw = upload<T>(ctx, w);
      auto dy = upload<float>(ctx, start);
      cuda::linear_accumulate(ctx, dx.data(), c.ldx, dw.data(), dy.data() + c.col0, c.ldy, c.M, c.N, c.K);
      const HostF out = download(ctx, dy);
      const ColumnBlock inside{c.ldy, c.col0, c.N};
      const std::string what = std::string("linear_accumulate ") + type_name<T>() + " M=" + std::to_string(c.M) +
                               " N=" + std::to_string(c.N) + " K=" + std::to_string(c.K);
      check_error(measure(out.data(), ref.data(), out.numel(), inside), {kF32Tol, kF32Tol * max_abs(y0)}, what);
      CHECK_MESSAGE(written_outside(out, inside) == 0, what);
      CHECK(plans_of(ctx, c.M, tuning == cuda::GemmTuning::All) == 1);
    }
  }
  cuda::Context ctx;
  Dev<T> x({4, 8}), w({6, 8}), w_bad({6, 7});
  Dev<float> y({4, 6}), y_bad({4, 5});
  CHECK_THROWS_WITH_AS(cuda::linear_accumulate(ctx, x, w_bad, y), doctest::Contains("does not end in K=7"),
                       epona::Error);
  CHECK_THROWS_WITH_AS(cuda::linear_accumulate(ctx, x, w, y_bad), doctest::Contains("output"), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::linear_accumulate(ctx, x.data(), 7, w.data(), y.data(), 6, 4, 6, 8),
                       doctest::Contains("row strides"), epona::Error);
}

TEST_CASE("cuda linear rejects bad shapes with epona::Error") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  Dev<float> x({4, 8}), w({6, 8}), w_bad({6, 7}), b({6}), b_bad({5}), y({4, 6}), y_bad({4, 5});
  Dev<float> none;
  CHECK_THROWS_WITH_AS(cuda::linear(ctx, x, w_bad, none, y), doctest::Contains("does not end in K=7"), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::linear(ctx, x, w, b_bad, y), doctest::Contains("bias"), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::linear(ctx, x, w, none, y_bad), doctest::Contains("output"), epona::Error);
  CHECK_THROWS_AS(cuda::linear(ctx, x.data(), 8, w.data(), b.data(), y.data(), 6, 4, 6, 0), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::linear(ctx, x.data(), 7, w.data(), b.data(), y.data(), 6, 4, 6, 8),
                       doctest::Contains("row strides"), epona::Error);
}

namespace {

// Whether the test is skipped (with a message) because the kernel `what` needs an sm_90a GPU
// and build.
bool skipped_without_sm90a(cuda::Context& ctx, const char* what) {
  if (cuda::detail::sm90a_available(ctx)) return false;
  MESSAGE((std::string("skipped: ") + what + " needs an sm_90a GPU and build"));
  return true;
}

// A product written by one of our own GEMMs into a column block of a wider (poisoned) buffer:
// x rows ldx apart, y's block at column col0 of rows ldy wide.
struct BlockCase {
  std::int64_t M, N, K, ldx, ldy, col0;
  bool bias;
  cuda::Epilogue epi;
  std::string name() const {
    return "M=" + std::to_string(M) + " N=" + std::to_string(N) + " K=" + std::to_string(K) + (bias ? " +bias " : " ") +
           epilogue_name(epi);
  }
};

// Runs run(x, w, bias or null, y + col0) on fresh random operands and checks the block against
// cpu::linear (the linear bound) and that nothing outside it was written. run returns whether
// it launched (a product it should take: REQUIREd).
template <class Run>
void check_block_product(cuda::Context& ctx, const BlockCase& c, std::uint32_t seed, const std::string& what,
                         Run run) {
  HostF xw = random_tensor({c.M, c.ldx}, seed, -2.f, 2.f);
  HostF w = random_tensor({c.N, c.K}, seed + 1, -1.f / std::sqrt(float(c.K)), 1.f / std::sqrt(float(c.K)));
  HostF b = c.bias ? random_tensor({c.N}, seed + 2) : HostF();
  round_to<bf16>(xw), round_to<bf16>(w);
  if (c.bias) round_to<bf16>(b);
  auto dx = upload<bf16>(ctx, xw), dw = upload<bf16>(ctx, w);
  auto db = c.bias ? upload<bf16>(ctx, b) : Dev<bf16>();
  Dev<bf16> dy({c.M, c.ldy});
  poison(ctx, dy);
  REQUIRE(run(dx.data(), dw.data(), c.bias ? db.data() : nullptr, dy.data() + c.col0));
  check_column_block<bf16>(download(ctx, dy), xw, c.ldx, w, c.bias ? b.data() : nullptr, c.M, c.N, c.K, c.ldy, c.col0,
                           c.epi, what + " " + c.name());
}

}  // namespace

// The own Hopper GEMM (gemm_wgmma.cuh) called directly, where cuda::linear would not pick it
// too: partial row and column tiles, a depth that is no whole number of stages, row strides
// with y a column block of a wider (poisoned) buffer, with and without bias, the erf GELU and
// no activation. Bound as for linear (the pre-activation rounded to bf16 first).
TEST_CASE("cuda own Hopper GEMM matches cpu::linear and writes only its block") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  if (skipped_without_sm90a(ctx, "the own GEMM")) return;
  const BlockCase cases[] = {
      {300, 520, 200, 200, 520, 0, true, cuda::Epilogue::GeluErf},      // partial tiles everywhere
      {515, 2048, 512, 512, 2048, 0, false, cuda::Epilogue::GeluErf},   // the DiTs' condition rows
      {128, 256, 64, 64, 256, 0, false, cuda::Epilogue::None},          // exactly one tile, one stage
      {1000, 4096, 1024, 1024, 4096, 0, true, cuda::Epilogue::None},    // several tiles per block
      {200, 136, 72, 80, 160, 8, true, cuda::Epilogue::GeluErf},        // strided x, y a column block
      {5150, 512, 128, 128, 512, 0, false, cuda::Epilogue::GeluErf},    // the MST's row count
  };
  std::uint32_t seed = 900;
  for (const BlockCase& c : cases)
    check_block_product(ctx, c, seed += 3, "own GEMM", [&](const bf16* x, const bf16* w, const bf16* b, bf16* y) {
      const auto run = [&](auto op) {
        return cuda::detail::own_gemm(ctx, x, c.ldx, w, b, y, c.ldy, c.M, c.N, c.K, op);
      };
      return c.epi == cuda::Epilogue::GeluErf ? run(cuda::detail::GeluErfOp{}) : run(cuda::detail::Identity{});
    });
}

// The few-rows GEMM (gemm_few_rows.cuh), every tile: partial row and column tiles, a depth that
// is no whole number of slices, fewer slices than a cluster has ranks (ranks with nothing to
// add), strided x and y a column block, bias, the tanh GELU and no activation.
TEST_CASE("cuda few-rows GEMM: every tile matches cpu::linear and writes only its block") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  if (skipped_without_sm90a(ctx, "the few-rows GEMM")) return;
  const BlockCase cases[] = {
      {515, 1024, 1024, 1024, 1024, 0, true, cuda::Epilogue::None},       // the TrajDiT's attention proj
      {300, 520, 200, 200, 520, 0, true, cuda::Epilogue::GeluTanh},       // partial tiles, depth 3 slices + 8
      {64, 128, 64, 64, 128, 0, false, cuda::Epilogue::None},             // one tile, one slice
      {130, 264, 136, 152, 400, 8, true, cuda::Epilogue::GeluTanh},       // strided x, y a column block
      {515, 512, 4096, 4096, 512, 0, false, cuda::Epilogue::GeluTanh},    // deep: many slices per rank
  };
  std::uint32_t seed = 1200;
  for (int choice = 0; choice < cuda::detail::fr::kChoices; ++choice)
    for (const BlockCase& c : cases)
      check_block_product(ctx, c, seed += 3, "few-rows tile " + std::to_string(choice),
                          [&](const bf16* x, const bf16* w, const bf16* b, bf16* y) {
                            return cuda::detail::few_rows_gemm(ctx, x, c.ldx, w, b, y, c.ldy, c.M, c.N, c.K, c.epi,
                                                               choice);
                          });
}

// Shapes and activations the few-rows GEMM refuses (nothing launched, false): cuda::linear then
// takes cuBLASLt.
TEST_CASE("cuda few-rows GEMM refuses what it cannot take") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  Dev<bf16> x({128, 64}), w({136, 64}), y({128, 136});
  const auto run = [&](std::int64_t N, cuda::Epilogue epi, int choice) {
    return cuda::detail::few_rows_gemm(ctx, x.data(), 64, w.data(), nullptr, y.data(), 136, 128, N, 64, epi, choice);
  };
  CHECK_FALSE(run(132, cuda::Epilogue::None, -1));     // N not a multiple of 8
  CHECK_FALSE(run(136, cuda::Epilogue::GeluErf, -1));  // an activation it lacks
  CHECK_FALSE(run(136, cuda::Epilogue::Silu, -1));
  CHECK_FALSE(run(136, cuda::Epilogue::None, cuda::detail::fr::kChoices));  // no such tile
  CHECK(run(136, cuda::Epilogue::None, -1) == cuda::detail::sm90a_available(ctx));
}

namespace {

// Spins for `ns` nanoseconds, then copies n elements: a producer that writes x late, launched
// programmatically (its wait_for_producer lets the next kernel start at once).
__global__ void late_copy_kernel(const bf16* src, bf16* dst, std::int64_t n, long long ns) {
  cuda::detail::wait_for_producer();
  long long start = 0, now = 0;
  asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(start));
  do asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(now));
  while (now - start < ns);
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < n; i += gridDim.x * blockDim.x)
    dst[i] = src[i];
}

}  // namespace

// The few-rows GEMM starts behind a programmatic edge. x written by a kernel that runs 200 µs
// late must still be read after it is written (x starts as NaN); so must w when the call says
// its w is not a parameter (early_weights false: nothing loaded before the wait).
TEST_CASE("cuda few-rows GEMM behind a late producer reads its operands after they are written") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  if (skipped_without_sm90a(ctx, "the few-rows GEMM")) return;
  const BlockCase c{515, 1024, 1024, 1024, 1024, 0, true, cuda::Epilogue::GeluTanh};
  for (int choice = 0; choice < cuda::detail::fr::kChoices; ++choice)
    for (const bool late_w : {false, true})
      check_block_product(ctx, c, 1300 + 3 * choice,
                          "few-rows tile " + std::to_string(choice) + (late_w ? " after a late w" : " after a late x"),
                          [&](const bf16* x, const bf16* w, const bf16* b, bf16* y) {
                            Dev<bf16> late(late_w ? Shape{c.N, c.K} : Shape{c.M, c.ldx});
                            poison(ctx, late);
                            cuda::detail::launch_after(late_copy_kernel, dim3(64), dim3(256), 0, ctx,
                                                       late_w ? w : x, late.data(), late.numel(), 200000LL);
                            const bool ran = cuda::detail::few_rows_gemm(
                                ctx, late_w ? x : late.data(), c.ldx, late_w ? late.data() : w, b, y, c.ldy, c.M, c.N,
                                c.K, c.epi, choice, /*early_weights=*/!late_w);
                            ctx.synchronize();  // `late` lives in this scope
                            return ran;
                          });
}

// With its switch on, cuda::linear sends the DiTs' condition-stream products to the few-rows
// GEMM (its choice of tile); the results match cpu::linear within the linear bound.
TEST_CASE("cuda linear with the few-rows switch on at the DiTs' shapes") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  ctx.policy().few_rows_gemm = true;
  check_linear<bf16>(ctx, {515, 3072, 1024, true, cuda::Epilogue::None}, 1400);      // qkv
  check_linear<bf16>(ctx, {515, 4096, 1024, true, cuda::Epilogue::GeluTanh}, 1401);  // mlp fc1 + GELU
  check_linear<bf16>(ctx, {515, 1024, 4096, true, cuda::Epilogue::None}, 1402);      // mlp fc2
  check_linear<bf16>(ctx, {530, 2048, 1024, false, cuda::Epilogue::None}, 1403);     // single-block kv
  check_linear<bf16>(ctx, {515, 1024, 1024, true, cuda::Epilogue::GeluErf}, 1404);   // not its: cuBLASLt + pass
}

// With its switch on, cuda::linear sends bf16 products with the erf GELU (at least a tile of
// rows) to the own GEMM; both paths (switch on and off) give the same values up to the
// summation order: at most one bf16 step apart before the GELU, so within the linear bound.
TEST_CASE("cuda linear with the erf GELU: own GEMM and cuBLASLt + pass agree") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  cpu::Context cctx;
  const std::int64_t M = 640, N = 1024, K = 768;
  HostF x = random_tensor({M, K}, 950, -2.f, 2.f), w = random_tensor({N, K}, 951, -0.04f, 0.04f);
  round_to<bf16>(x), round_to<bf16>(w);
  auto dx = upload<bf16>(ctx, x), dw = upload<bf16>(ctx, w);
  Dev<bf16> none, on({M, N}), off({M, N});
  poison(ctx, on), poison(ctx, off);
  for (const bool own : {true, false}) {
    ctx.policy().own_gemm = own;
    cuda::linear(ctx, dx, dw, none, own ? on : off, cuda::Epilogue::GeluErf);
  }
  HostF z({M, N}), y({M, N});
  cpu::linear(cctx, x, w, HostF(), z, cpu::Epilogue::None);
  cpu::linear(cctx, x, w, HostF(), y, cpu::Epilogue::GeluErf);
  const HostF a = download(ctx, on), b = download(ctx, off);
  check_error(measure(a, y), linear_bound<bf16>(cuda::Epilogue::GeluErf, z, y), "linear gelu_erf, own GEMM on");
  check_error(measure(b, y), linear_bound<bf16>(cuda::Epilogue::GeluErf, z, y), "linear gelu_erf, own GEMM off");
  check_error(measure(a, b), linear_bound<bf16>(cuda::Epilogue::GeluErf, z, y), "own GEMM against cuBLASLt + pass");
}
