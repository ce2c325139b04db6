// epona/cpu/cpu_features.hpp — which x86 vector extensions this CPU and its OS offer (cpuid +
// xgetbv, and for AMX the kernel's tile permission), and which GEMM kernel family the library
// runs: the best available (AMX > AVX512-BF16 > AVX-512 > AVX2 > generic), or another forced
// with EPONA_CPU_ISA=generic|avx2|avx512|avx512bf16|amx (tests, comparisons, a faulty CPU).
#pragma once

#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <string_view>

#if defined(__x86_64__) || defined(__i386__)
#include <cpuid.h>
#endif
#if defined(__linux__)
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include "epona/core/error.hpp"

namespace epona::cpu {

// The kernel families, lowest first. Generic: Eigen, compiled for the build's target.
// Avx2: AVX2 + FMA micro-kernels. Avx512: AVX-512 F/BW/DQ/VL micro-kernels (bf16 weights
// widened to float32 while packing). Avx512Bf16: as Avx512, but bf16 weights multiply with
// AVX512-BF16 dot products (activations rounded to bf16; fp32 accumulation). Amx: as
// Avx512Bf16 with the bf16 products on Sapphire Rapids' AMX tiles (float32 weights run the
// AVX-512 kernels under it). Each family needs every extension of the ones below it, so
// "the best" is one name and every lower one is a fallback the same CPU can run.
enum class Isa : int { Generic = 0, Avx2 = 1, Avx512 = 2, Avx512Bf16 = 3, Amx = 4 };

inline const char* isa_name(Isa isa) {
  switch (isa) {
    case Isa::Generic: return "generic";
    case Isa::Avx2: return "avx2";
    case Isa::Avx512: return "avx512";
    case Isa::Avx512Bf16: return "avx512bf16";
    case Isa::Amx: return "amx";
  }
  return "?";
}

struct CpuFeatures {
  bool avx2_fma = false;     // AVX2 and FMA3, with the OS saving ymm state
  bool avx512 = false;       // AVX-512 F, BW, DQ, VL, with the OS saving zmm and mask state
  bool avx512_bf16 = false;  // AVX512_BF16 (vdpbf16ps, vcvtne2ps2bf16)
  bool amd = false;          // "AuthenticAMD": Zen 4/5 run a 512-bit FMA as two 256-bit halves
  bool amx_bf16 = false;     // AMX tiles + BF16 with the OS supporting tile state (XCR0)
  bool amx_permitted = false;  // Linux granted this process the tile data (asked only when amx_bf16)

  // The highest family this CPU can run: AMX > AVX512-BF16 > AVX-512 > AVX2 > generic. AMX
  // also needs AVX512-BF16 (its A panels are rounded with vcvtne2ps2bf16) and the permission.
  Isa best() const {
    if (avx512 && avx512_bf16 && amx_bf16 && amx_permitted) return Isa::Amx;
    if (avx512 && avx512_bf16) return Isa::Avx512Bf16;
    if (avx512) return Isa::Avx512;
    if (avx2_fma) return Isa::Avx2;
    return Isa::Generic;
  }
  bool supports(Isa isa) const;
};

namespace detail {
// Linux lends the AMX tile state to a process only on request (arch_prctl); asked once, while
// the features are detected, and only on a CPU whose XCR0 has the tile state.
inline bool request_amx_permission() {
#if defined(__linux__) && defined(__x86_64__)
  constexpr long kReqXcompPerm = 0x1023, kXfeatureXtiledata = 18;
  return syscall(SYS_arch_prctl, kReqXcompPerm, kXfeatureXtiledata) == 0;
#else
  return false;
#endif
}
}  // namespace detail

inline bool CpuFeatures::supports(Isa isa) const { return static_cast<int>(isa) <= static_cast<int>(best()); }

namespace detail {
#if defined(__x86_64__) || defined(__i386__)
struct CpuidRegs {
  unsigned a = 0, b = 0, c = 0, d = 0;
};
inline CpuidRegs cpuid(unsigned leaf, unsigned subleaf) {
  CpuidRegs r;
  if (!__get_cpuid_count(leaf, subleaf, &r.a, &r.b, &r.c, &r.d)) r = {};
  return r;
}
// XCR0: which register states the OS saves on a context switch (an instruction whose state
// the OS does not save must not be used even when cpuid lists it).
inline std::uint64_t xcr0() {
  std::uint32_t lo, hi;
  __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
  return (std::uint64_t{hi} << 32) | lo;
}
#endif
inline bool bit(unsigned reg, int n) { return (reg >> n) & 1u; }
}  // namespace detail

inline CpuFeatures detect_cpu_features() {
  CpuFeatures f;
#if defined(__x86_64__) || defined(__i386__)
  using detail::bit;
  const auto l1 = detail::cpuid(1, 0);
  if (!bit(l1.c, 27)) return f;  // no OSXSAVE: xgetbv unavailable, no AVX at all
  const std::uint64_t xcr = detail::xcr0();
  const bool ymm_state = (xcr & 0x6) == 0x6;         // SSE + AVX state
  const bool zmm_state = ymm_state && (xcr & 0xe0) == 0xe0;  // opmask, ZMM_Hi256, Hi16_ZMM
  const auto l0 = detail::cpuid(0, 0);
  f.amd = l0.b == 0x68747541u && l0.d == 0x69746e65u && l0.c == 0x444d4163u;  // "Auth" "enti" "cAMD"
  if (l0.a < 7) return f;
  const auto l7 = detail::cpuid(7, 0);
  f.avx2_fma = ymm_state && bit(l1.c, 28) /*avx*/ && bit(l1.c, 12) /*fma*/ && bit(l7.b, 5) /*avx2*/;
  f.avx512 = f.avx2_fma && zmm_state && bit(l7.b, 16) /*f*/ && bit(l7.b, 17) /*dq*/ && bit(l7.b, 30) /*bw*/ &&
             bit(l7.b, 31) /*vl*/;
  if (f.avx512 && l7.a >= 1) f.avx512_bf16 = bit(detail::cpuid(7, 1).a, 5);
  f.amx_bf16 = bit(l7.d, 22) && bit(l7.d, 24) && (xcr & 0x60000) == 0x60000;  // XTILECFG, XTILEDATA
  f.amx_permitted = f.amx_bf16 && detail::request_amx_permission();
#endif
  return f;
}

inline const CpuFeatures& cpu_features() {
  static const CpuFeatures f = detect_cpu_features();
  return f;
}

// "generic" | "avx2" | "avx512" | "avx512bf16" | "amx" (case-sensitive); anything else is an error.
inline Isa parse_isa(std::string_view s) {
  for (Isa isa : {Isa::Generic, Isa::Avx2, Isa::Avx512, Isa::Avx512Bf16, Isa::Amx})
    if (s == isa_name(isa)) return isa;
  fail("EPONA_CPU_ISA='", std::string(s), "' is not one of generic, avx2, avx512, avx512bf16, amx");
}

namespace detail {
inline constexpr int kIsaUnset = -1;
inline std::atomic<int>& isa_override() {
  static std::atomic<int> v{kIsaUnset};
  return v;
}
inline Isa checked_isa(Isa want, const char* source) {
  const CpuFeatures& f = cpu_features();
  EPONA_CHECK(f.supports(want), source, " asks for the '", isa_name(want), "' kernels, but this CPU offers at most '",
              isa_name(f.best()), "'", want == Isa::Amx ? " (AMX needs AMX-BF16, AVX512-BF16 and the OS's permission)" : "");
  return want;
}
}  // namespace detail

// The kernel family an EPONA_CPU_ISA value selects: unset or empty is the best available; a
// name the CPU cannot run, or no name at all, is an error.
inline Isa isa_from_setting(const char* value) {
  if (!value || !*value) return cpu_features().best();
  return detail::checked_isa(parse_isa(value), "EPONA_CPU_ISA");
}

namespace detail {
// The environment's choice, read once.
inline Isa env_isa() {
  static const Isa isa = isa_from_setting(std::getenv("EPONA_CPU_ISA"));
  return isa;
}
}  // namespace detail

// The kernel family every GEMM uses now: set_isa's choice, else EPONA_CPU_ISA, else the best.
inline Isa active_isa() {
  const int o = detail::isa_override().load(std::memory_order_relaxed);
  return o == detail::kIsaUnset ? detail::env_isa() : static_cast<Isa>(o);
}

// Forces a kernel family for the whole process (an error when the CPU lacks it).
inline void set_isa(Isa isa) {
  detail::isa_override().store(static_cast<int>(detail::checked_isa(isa, "set_isa")), std::memory_order_relaxed);
}
// Back to EPONA_CPU_ISA or the best available.
inline void reset_isa() { detail::isa_override().store(detail::kIsaUnset, std::memory_order_relaxed); }

// Sets a kernel family for a scope (tests and benchmarks comparing the paths).
class ScopedIsa {
 public:
  explicit ScopedIsa(Isa isa) : previous_(detail::isa_override().load()) { set_isa(isa); }
  ~ScopedIsa() { detail::isa_override().store(previous_); }
  ScopedIsa(const ScopedIsa&) = delete;
  ScopedIsa& operator=(const ScopedIsa&) = delete;

 private:
  int previous_;
};

}  // namespace epona::cpu
