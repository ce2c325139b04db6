// The run-time choice of GEMM kernels (epona/cpu/cpu_features.hpp) and its fallbacks: the
// default chain AMX > AVX512-BF16 > AVX-512 > AVX2 > generic on synthetic feature sets; every
// kernel family forced in turn (set_isa / ScopedIsa, what EPONA_CPU_ISA does) gives linear's
// float64 result; a family the CPU lacks is refused with a message, never run; EPONA_CPU_ISA
// values are parsed strictly. "No illegal instruction on an older CPU": in a portable build
// (no -march=native, so only the dispatched kernels use AVX-512), this program re-runs its
// "best kernels" case under valgrind, whose emulated CPU reports AVX2 but no AVX-512 — an
// AVX-512 instruction reached there would stop valgrind with SIGILL.
#include <doctest/doctest.h>

#include <cmath>
#include <cstdlib>
#include <string>
#include <vector>

#include <unistd.h>

#include "epona/core/error.hpp"
#include "epona/cpu/gemm.hpp"
#include "testing.hpp"

using namespace epona;
using cpu::Epilogue;
using cpu::Isa;

namespace {

constexpr Isa kAllIsas[] = {Isa::Generic, Isa::Avx2, Isa::Avx512, Isa::Avx512Bf16, Isa::Amx};

double gelu_tanh(double x) { return 0.5 * x * (1.0 + std::tanh(std::sqrt(2.0 / M_PI) * (x + 0.044715 * x * x * x))); }

// linear<W> with bias and GELU-tanh at a few shapes (dot rows, every tile edge), against
// float64: max |got − ref| / max |ref| <= tol.
template <class W>
void check_linear_matches_float64(double tol) {
  for (auto [M, N, K] : {std::tuple<std::int64_t, std::int64_t, std::int64_t>{3, 40, 33}, {37, 70, 129},
                         {131, 100, 520}, {6, 65, 17}}) {
    cpu::Context ctx(2);
    const auto x = test::random_floats(static_cast<std::size_t>(M * K), 31);
    const auto wf = test::random_floats(static_cast<std::size_t>(N * K), 32, -0.2f, 0.2f);
    const auto bf = test::random_floats(static_cast<std::size_t>(N), 33);
    std::vector<W> w(wf.size()), b(bf.size());
    for (std::size_t i = 0; i < wf.size(); ++i) w[i] = W(wf[i]);
    for (std::size_t i = 0; i < bf.size(); ++i) b[i] = W(bf[i]);
    std::vector<float> y(static_cast<std::size_t>(M * N));
    cpu::linear<W>(ctx, x.data(), K, w.data(), b.data(), y.data(), N, M, N, K, Epilogue::GeluTanh);
    std::vector<double> ref(y.size());
    for (std::int64_t m = 0; m < M; ++m)
      for (std::int64_t n = 0; n < N; ++n) {
        double acc = double(float(b[n]));
        for (std::int64_t k = 0; k < K; ++k) acc += double(x[m * K + k]) * double(float(w[n * K + k]));
        ref[m * N + n] = gelu_tanh(acc);
      }
    CAPTURE(M);
    CAPTURE(N);
    CAPTURE(K);
    CHECK(test::rel_max(y, ref) <= tol);
  }
}

// bf16 weights on the dot-product path round the activations (gemm_bf16.cpp): here a bound
// for K <= 520 from its ε_K, relative to the largest output (outputs are O(1)).
double bf16_tolerance(Isa isa) { return isa == Isa::Avx512Bf16 || isa == Isa::Amx ? 2e-2 : 1e-5; }

}  // namespace

TEST_CASE("every kernel family this CPU offers can be forced and gives the float64 result") {
  const cpu::CpuFeatures& f = cpu::cpu_features();
  MESSAGE("detected: avx2+fma ", f.avx2_fma, ", avx512 ", f.avx512, ", avx512_bf16 ", f.avx512_bf16, " -> best '",
          cpu::isa_name(f.best()), "'");
  for (Isa isa : kAllIsas) {
    CAPTURE(cpu::isa_name(isa));
    if (!f.supports(isa)) {
      CHECK_THROWS_WITH_AS(cpu::set_isa(isa), doctest::Contains(cpu::isa_name(isa)), Error);
      continue;
    }
    cpu::ScopedIsa scoped(isa);
    CHECK(cpu::active_isa() == isa);
    check_linear_matches_float64<float>(1e-5);
    check_linear_matches_float64<bf16>(bf16_tolerance(isa));
  }
}

TEST_CASE("the default is the highest family the CPU and OS offer: AMX > AVX512-BF16 > AVX-512 > AVX2 > generic") {
  // best() on feature sets with one capability taken away at a time: each falls back one step.
  cpu::CpuFeatures f;
  f.avx2_fma = f.avx512 = f.avx512_bf16 = f.amx_bf16 = f.amx_permitted = true;
  CHECK(f.best() == Isa::Amx);
  for (Isa isa : kAllIsas) CHECK(f.supports(isa));
  f.amx_permitted = false;  // the tile unit is there, but Linux refused the tile state
  CHECK(f.best() == Isa::Avx512Bf16);
  CHECK_FALSE(f.supports(Isa::Amx));
  f.amx_permitted = true;
  f.avx512_bf16 = false;  // AMX without AVX512-BF16 (its A packing needs vcvtne2ps2bf16)
  CHECK(f.best() == Isa::Avx512);
  f.amx_bf16 = false;
  CHECK(f.best() == Isa::Avx512);
  f.avx512 = false;
  CHECK(f.best() == Isa::Avx2);
  CHECK(f.supports(Isa::Generic));
  CHECK_FALSE(f.supports(Isa::Avx512));
  f.avx2_fma = false;
  CHECK(f.best() == Isa::Generic);
  CHECK_FALSE(f.supports(Isa::Avx2));

  // This CPU: AMX is the default exactly when the tile unit, AVX512-BF16 and the permission are there.
  const cpu::CpuFeatures& here = cpu::cpu_features();
  MESSAGE("amx_bf16 ", here.amx_bf16, ", permitted ", here.amx_permitted, " -> default '",
          std::string(cpu::isa_name(cpu::isa_from_setting(nullptr))), "'");
  CHECK((here.best() == Isa::Amx) == (here.avx512 && here.avx512_bf16 && here.amx_bf16 && here.amx_permitted));
  CHECK(here.amx_permitted <= here.amx_bf16);  // permission is asked only where XCR0 has the tile state
  if (!std::getenv("EPONA_CPU_ISA")) {
    cpu::reset_isa();
    CHECK(cpu::active_isa() == here.best());
  }
}

TEST_CASE("linear on this CPU's best kernels") {
  // Also the case the valgrind run below executes on an emulated AVX2-only CPU.
  cpu::ScopedIsa scoped(cpu::cpu_features().best());
  check_linear_matches_float64<float>(1e-5);
  check_linear_matches_float64<bf16>(bf16_tolerance(cpu::active_isa()));
}

TEST_CASE("ScopedIsa restores the previous choice; reset_isa returns to the environment's") {
  const Isa before = cpu::active_isa();
  {
    cpu::ScopedIsa generic(Isa::Generic);
    CHECK(cpu::active_isa() == Isa::Generic);
  }
  CHECK(cpu::active_isa() == before);
  cpu::set_isa(Isa::Generic);
  cpu::reset_isa();
  CHECK(cpu::active_isa() == cpu::isa_from_setting(std::getenv("EPONA_CPU_ISA")));
}

TEST_CASE("EPONA_CPU_ISA values: names, empty, unknown, beyond the CPU") {
  for (Isa isa : kAllIsas) CHECK(cpu::parse_isa(cpu::isa_name(isa)) == isa);
  CHECK(cpu::isa_from_setting(nullptr) == cpu::cpu_features().best());
  CHECK(cpu::isa_from_setting("") == cpu::cpu_features().best());
  CHECK(cpu::isa_from_setting("generic") == Isa::Generic);
  CHECK_THROWS_WITH_AS(cpu::isa_from_setting("AVX512"), doctest::Contains("EPONA_CPU_ISA='AVX512'"), Error);
  CHECK_THROWS_WITH_AS(cpu::isa_from_setting("sse"), doctest::Contains("generic, avx2, avx512, avx512bf16"), Error);
  for (Isa isa : kAllIsas)
    if (!cpu::cpu_features().supports(isa))
      CHECK_THROWS_WITH_AS(cpu::isa_from_setting(cpu::isa_name(isa)), doctest::Contains("this CPU offers at most"),
                           Error);
}

TEST_CASE("a portable build runs on a CPU without AVX-512 (valgrind's emulated CPU)") {
#if defined(__AVX512F__)
  MESSAGE("built with AVX-512 enabled everywhere (-march=native): the fallback check needs a portable build "
          "(EPONA_NATIVE=OFF, e.g. -march=x86-64-v3)");
#else
  if (std::getenv("EPONA_UNDER_VALGRIND")) return;  // this is the run under valgrind
  if (std::system("valgrind --version > /dev/null 2>&1") != 0) {
    MESSAGE("valgrind not found: fallback run skipped");
    return;
  }
  const std::string cmd =
      "EPONA_UNDER_VALGRIND=1 valgrind -q --tool=none /proc/" + std::to_string(::getpid()) +
      "/exe --test-case='linear on this CPU*best kernels' > /dev/null 2>&1";
  // /proc/<pid>/exe resolves to this very program.
  const int rc = std::system(cmd.c_str());
  CAPTURE(cmd);
  CHECK(rc == 0);
#endif
}
