// Tests for epona/cpu/gemm_kernels.hpp and gemm_driver.hpp: every micro-kernel family this CPU
// can run (AVX2 6×16; AVX-512 14×32 and 6×64; their BF16 dot-product twins; AMX 32×32 where
// present, and always with emulated tile instructions), driven through
// linear's packing and the blocked, threaded driver, against a float64 loop. Sizes cover the
// edges of every tile (rows 1..MR+1, columns across the 16-lane masks), several K blocks, odd K,
// one and several threads, and the shared-B plan (fewer column tasks than threads). The
// AVX-512 16×16 transposes are checked word for word against the portable packing.
// Tolerances: float32 kernels max |got − ref| / max |ref| <= 1e-5 (fp32 accumulation over up
// to 700 terms); bf16 kernels per element within the fp32 accumulation bound of the exact
// bf16-rounded product (gemm_bf16.cpp states and tests the bound against float32).
#include <doctest/doctest.h>

#include <cmath>
#include <cstring>
#include <map>
#include <string>
#include <tuple>
#include <vector>

#include "epona/cpu/gemm.hpp"
#include "testing.hpp"

using namespace epona;
using cpu::Epilogue;

namespace {

struct Family {
  std::string name;
  const cpu::gemm::KernelFamily* f;
};

// AMX's tile instructions written from their definition (Intel SDM: TILELOADD, TILESTORED,
// TILEZERO, TDPBF16PS; tiles of 16 rows × 64 bytes), so the AMX kernel's data layout, K tiling
// and edges are tested on any CPU; the instructions themselves run where the CPU has them.
struct EmulatedTiles {
  using Word = cpu::gemm::Word;
  Word tile[8][16][16] = {};
  void configure() {}
  void release() {}
  template <int T>
  void load(const void* p, std::int64_t stride) {
    for (int r = 0; r < 16; ++r) std::memcpy(tile[T][r], static_cast<const char*>(p) + r * stride, 64);
  }
  template <int T>
  void store(void* p, std::int64_t stride) {
    for (int r = 0; r < 16; ++r) std::memcpy(static_cast<char*>(p) + r * stride, tile[T][r], 64);
  }
  template <int T>
  void zero() {
    std::memset(tile[T], 0, sizeof tile[T]);
  }
  static float half(Word w, int which) { return bf16::to_float(static_cast<std::uint16_t>(which ? w >> 16 : w & 0xffffu)); }
  // C[m][n] += Σ_p A[m].bf16[2p]·B[p].bf16[2n] + A[m].bf16[2p+1]·B[p].bf16[2n+1], in float32.
  template <int C, int A, int B>
  void dot() {
    for (int m = 0; m < 16; ++m)
      for (int n = 0; n < 16; ++n) {
        float acc;
        std::memcpy(&acc, &tile[C][m][n], 4);
        for (int p = 0; p < 16; ++p) {
          acc += half(tile[A][m][p], 0) * half(tile[B][p][n], 0);
          acc += half(tile[A][m][p], 1) * half(tile[B][p][n], 1);
        }
        std::memcpy(&tile[C][m][n], &acc, 4);
      }
  }
};

const cpu::gemm::KernelFamily& amx_emulated() {
  static const cpu::gemm::KernelFamily f = [] {
    auto fam = cpu::gemm::make_amx_family<EmulatedTiles>(std::make_integer_sequence<int, 32>{});
    fam.avx512_packing = cpu::cpu_features().supports(cpu::Isa::Avx512Bf16);  // else the portable packers
    return fam;
  }();
  return f;
}

// The families this CPU can execute.
std::vector<Family> runnable_families() {
  std::vector<Family> out;
#if defined(EPONA_GEMM_X86)
  const auto& feat = cpu::cpu_features();
  if (feat.avx2_fma) out.push_back({"avx2 6x16", &cpu::gemm::avx2_f32()});
  if (feat.avx512) {
    out.push_back({"avx512 14x32", &cpu::gemm::avx512_f32(cpu::gemm::Tile::Tall)});
    out.push_back({"avx512 6x64", &cpu::gemm::avx512_f32(cpu::gemm::Tile::Wide)});
  }
  if (feat.avx512 && feat.avx512_bf16) {
    out.push_back({"avx512bf16 14x32", &cpu::gemm::avx512_bf16(cpu::gemm::Tile::Tall)});
    out.push_back({"avx512bf16 6x64", &cpu::gemm::avx512_bf16(cpu::gemm::Tile::Wide)});
  }
  if (feat.supports(cpu::Isa::Amx)) out.push_back({"amx 32x32", &cpu::gemm::amx_bf16()});
  out.push_back({"amx 32x32 (emulated tiles)", &amx_emulated()});
#endif
  return out;
}

double round_bf16(float v) { return double(float(bf16(v))); }

// y = act(x·wᵀ + b) in float64; `pairs`: x rounded to bf16 first (what the BF16 kernels
// multiply). Also returns Σ|x_k w_k| per element for the accumulation bound.
struct Reference {
  std::vector<double> y, abs_sum;
};
template <class W>
Reference reference(const std::vector<float>& x, const std::vector<W>& w, const std::vector<float>& b, std::int64_t M,
                    std::int64_t N, std::int64_t K, bool pairs) {
  Reference r{std::vector<double>(static_cast<std::size_t>(M * N)), std::vector<double>(static_cast<std::size_t>(M * N))};
  for (std::int64_t m = 0; m < M; ++m)
    for (std::int64_t n = 0; n < N; ++n) {
      double acc = b.empty() ? 0.0 : b[n], mag = 0;
      for (std::int64_t k = 0; k < K; ++k) {
        const double xv = pairs ? round_bf16(x[m * K + k]) : double(x[m * K + k]);
        const double p = xv * double(float(w[n * K + k]));
        acc += p;
        mag += std::abs(p);
      }
      r.y[m * N + n] = acc;
      r.abs_sum[m * N + n] = mag;
    }
  return r;
}

// The float64 reference depends only on the (deterministic) inputs, not on the family or the
// thread count: computed once per product (most of this program's time under the sanitizers).
template <class W>
const Reference& cached_reference(const std::vector<float>& x, const std::vector<W>& w, const std::vector<float>& b,
                                  std::int64_t M, std::int64_t N, std::int64_t K, bool pairs) {
  static std::map<std::tuple<std::int64_t, std::int64_t, std::int64_t, bool>, Reference> cache;
  const auto key = std::make_tuple(M, N, K, pairs);
  auto it = cache.find(key);
  if (it == cache.end()) it = cache.emplace(key, reference(x, w, b, M, N, K, pairs)).first;
  return it->second;
}

template <class W>
std::vector<W> random_weights(std::int64_t n, std::uint32_t seed, float amp) {
  const auto v = test::random_floats(static_cast<std::size_t>(n), seed, -amp, amp);
  std::vector<W> w(v.size());
  for (std::size_t i = 0; i < v.size(); ++i) w[i] = W(v[i]);
  return w;
}

// Runs one product through the family and checks it; bias added (no activation: the epilogue
// functors are tested through linear in gemm.cpp).
template <class W>
void check_family(const Family& fam, std::int64_t M, std::int64_t N, std::int64_t K, int threads) {
  const bool pairs = fam.f->k_per_step == 2;
  if (pairs && !std::is_same_v<W, bf16>) return;  // the dot-product kernels take bf16 weights only
  const auto x = test::random_floats(static_cast<std::size_t>(M * K), 11 + static_cast<std::uint32_t>(M * 7 + K));
  const auto w = random_weights<W>(N * K, 12 + static_cast<std::uint32_t>(N), 1.0f / std::sqrt(float(K)));
  const auto b = test::random_floats(static_cast<std::size_t>(N), 13);
  std::vector<float> y(static_cast<std::size_t>(M * N), std::nanf(""));
  cpu::detail::linear_packed<W>(*fam.f, threads, x.data(), K, w.data(), b.data(), y.data(), N, M, N, K, Epilogue::None);
  const Reference& ref = cached_reference(x, w, b, M, N, K, pairs);
  CAPTURE(fam.name);
  CAPTURE(M);
  CAPTURE(N);
  CAPTURE(K);
  CAPTURE(threads);
  if (!pairs) {
    CHECK(test::rel_max(y, ref.y) <= 1e-5);
    return;
  }
  // fp32 accumulation of exact bf16 products (K products, a sum per K block, the bias):
  // |err| <= (K + 8)·2^-24·(Σ|x̂ w| + |b|), |b| < 1.
  int bad = 0;
  for (std::size_t i = 0; i < y.size(); ++i) {
    const double bound = (double(K) + 8) * 0x1p-24 * (ref.abs_sum[i] + 1.0) + 1e-30;
    if (!(std::abs(double(y[i]) - ref.y[i]) <= bound)) ++bad;
  }
  CHECK(bad == 0);
}

}  // namespace

TEST_CASE("every runnable micro-kernel family matches float64 at tile edges, K blocks and thread counts") {
  const auto families = runnable_families();
  if (families.empty()) MESSAGE("no x86 micro-kernel family runs on this CPU: only the generic path is used");
  for (const Family& fam : families) {
    const std::int64_t mr = fam.f->mr, nr = fam.f->nr;
    // Rows: 1, MR-1, MR, MR+1 and more; columns across the masks; K across blocks and odd.
    for (std::int64_t M : {std::int64_t{1}, mr - 1, mr, mr + 1, 2 * mr + 3, std::int64_t{131}})
      for (std::int64_t N : {std::int64_t{1}, std::int64_t{15}, std::int64_t{17}, nr, nr + 1, 3 * nr - 5})
        for (std::int64_t K : {std::int64_t{1}, std::int64_t{2}, std::int64_t{3}, std::int64_t{33}, std::int64_t{700}}) {
          if (M <= 0) continue;
          check_family<float>(fam, M, N, K, 1);
          check_family<bf16>(fam, M, N, K, 1);
        }
  }
}

TEST_CASE("threaded plans: column tasks, rows split with a shared packed B, several K blocks") {
  for (const Family& fam : runnable_families())
    for (int threads : {2, 3, 8})
      for (auto [M, N, K] : {std::tuple<std::int64_t, std::int64_t, std::int64_t>{300, 1000, 520},  // column tasks
                             {301, 40, 1100},   // few column panels: rows split, B packed once (shared)
                             {64, 16, 600},     // one column panel
                             {9, 700, 3}}) {    // tiny K
        check_family<float>(fam, M, N, K, threads);
        check_family<bf16>(fam, M, N, K, threads);
      }
}

TEST_CASE("the plan covers the output exactly once") {
  const cpu::gemm::KernelFamily fam{14, 32, false, 1, 256, 256, {}};
  for (int threads : {1, 2, 16})
    for (auto [M, N, S] : {std::tuple<std::int64_t, std::int64_t, std::int64_t>{1310, 1024, 1024},
                           {128, 3072, 1024}, {15, 512, 512}, {131, 32, 1024}, {1, 1, 1}, {5000, 3, 9}}) {
      const auto p = cpu::gemm::plan_gemm(fam, M, N, S, threads);
      CAPTURE(M);
      CAPTURE(N);
      CAPTURE(threads);
      CHECK(p.m_per_task * p.m_tasks >= p.m_panels);
      CHECK(p.m_per_task * (p.m_tasks - 1) < p.m_panels);
      CHECK(p.n_per_task * p.n_tasks >= p.n_panels);
      CHECK(p.n_per_task * (p.n_tasks - 1) < p.n_panels);
      CHECK(p.kc * p.k_blocks >= S);
      CHECK(p.kc <= fam.kc);
      CHECK(p.threads >= 1);
      CHECK(p.threads <= std::max(1, threads));
      CHECK(p.shared_b == (p.m_tasks > 1));
    }
}

#if defined(EPONA_GEMM_X86)
TEST_CASE("AVX-512 packing equals the portable packing word for word") {
  if (!cpu::cpu_features().avx512) {
    MESSAGE("no AVX-512 on this CPU: its packing is not exercised");
    return;
  }
  using cpu::gemm::Word;
  const std::int64_t ld = 80;
  const auto src = test::random_floats(static_cast<std::size_t>(40 * ld), 21);
  std::vector<bf16> src16(src.size());
  for (std::size_t i = 0; i < src.size(); ++i) src16[i] = bf16(src[i]);
  for (std::int64_t R : {6, 14, 32, 64})
    for (std::int64_t rows : {std::int64_t{1}, R - 1, R})
      for (auto [s0, steps] : {std::pair<std::int64_t, std::int64_t>{0, 17}, {5, 16}, {3, 31}, {0, 1}}) {
        if (rows <= 0 || rows > 40) continue;
        const std::size_t n = static_cast<std::size_t>(R * steps);
        std::vector<Word> got(n, 0xdeadbeefu), want(n, 0xfeedfaceu);
        CAPTURE(R);
        CAPTURE(rows);
        CAPTURE(s0);
        CAPTURE(steps);
        cpu::gemm::pack_f32_avx512(src.data(), ld, rows, R, s0, steps, got.data());
        cpu::gemm::pack_transposed(src.data(), ld, rows, R, s0, steps, want.data(), cpu::gemm::FloatStep{});
        CHECK(got == want);
        cpu::gemm::pack_bf16_widened_avx512(src16.data(), ld, rows, R, s0, steps, got.data());
        cpu::gemm::pack_transposed(src16.data(), ld, rows, R, s0, steps, want.data(), cpu::gemm::FloatStep{});
        CHECK(got == want);
        // bf16 pairs as stored: rows of ld (even) bf16 values
        cpu::gemm::pack_bf16_pairs_avx512(src16.data(), ld, rows, R, s0, steps, got.data());
        cpu::gemm::pack_transposed(src16.data(), ld, rows, R, s0, steps, want.data(), cpu::gemm::Bf16PairStep{ld});
        CHECK(got == want);
        if (cpu::cpu_features().avx512_bf16 && R <= 16) {  // A panels only (R = MR)
          const std::int64_t K = 2 * (s0 + steps) - 1;        // odd: the last pair is half empty
          cpu::gemm::pack_bf16_pairs_rounded(src.data(), ld, rows, R, K, s0, steps, got.data());
          cpu::gemm::pack_transposed(src.data(), ld, rows, R, s0, steps, want.data(), cpu::gemm::Bf16PairStep{K});
          CHECK(got == want);
        }
      }
}
#endif
