// epona/cuda/ptx/wgmma.cuh — the Hopper (sm_90a) instructions our warp-specialised kernels share
// (the TMA flash attention, the fused-epilogue GEMM): wgmma shared-memory descriptors and
// issue/commit/wait, mbarriers with transaction counts, TMA tile loads, and the driver's
// tensor-map encoder. The asm needs an sm_90a target; callers compile it only there.
#pragma once

#include <cuda.h>  // CUtensorMap (the encoder itself is fetched from the driver at run time)
#include <cuda_runtime.h>

#include <cstdint>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/ptx/mma.cuh"

namespace epona::cuda::detail {

// Marks sm_90a code (mark_build), which has the wgmma kernels.
// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void wgmma_marker_kernel(int* flag) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  mark_build(flag);
#else
  (void)flag;
#endif
}

// Whether this GPU runs sm_90a code from this binary (the wgmma / TMA kernels).
inline bool sm90a_available(const Context& ctx) {
  if (ctx.info().major != 9 || ctx.info().minor != 0) return false;  // sm_90a code runs on 9.0 only
  static const bool built = build_marked(wgmma_marker_kernel<>);
  return built;
}

// The 128-byte swizzle's geometry: 128-byte rows in 8-row atoms of 1024 bytes; a swizzled tile
// starts at an atom boundary, so the swizzle's phase is the address's own.
constexpr int kRowBytes = 128;
constexpr int kAtomBytes = 8 * kRowBytes;
// The first atom boundary in a dynamic shared-memory buffer (kAtomBytes of slack reserved).
__device__ __forceinline__ unsigned first_atom(const void* smem) {
  return (smem_addr(smem) + kAtomBytes - 1) & ~unsigned{kAtomBytes - 1};
}

// wgmma shared-memory matrix descriptor with the 128-byte swizzle. K-major operands (Q, K):
// `lead` unused, `stride` = 1024 (from one 8-row atom to the next). N-major V: `lead` = the
// distance between the two 64-channel halves, `stride` = 1024 (from one 8-key atom to the next).
__device__ __forceinline__ std::uint64_t smem_desc(unsigned addr, unsigned lead, unsigned stride) {
  return std::uint64_t{(addr & 0x3FFFFu) >> 4} | std::uint64_t{lead >> 4} << 16 | std::uint64_t{stride >> 4} << 32 |
         std::uint64_t{1} << 62;
}

__device__ __forceinline__ void wgmma_fence() { asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory"); }
__device__ __forceinline__ void wgmma_commit() { asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory"); }
__device__ __forceinline__ void wgmma_wait_all() { asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); }
// Makes the shared memory this thread's cp.async wrote visible to the tensor cores' (async) proxy.
__device__ __forceinline__ void fence_proxy_async() { asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory"); }

// Pins accumulator registers at this point of the program: the compiler sees the wgmma asm
// write them when it is issued, so without this it could read them before wgmma_wait_all.
template <int N>
__device__ __forceinline__ void pin(float (&d)[N][4]) {
#pragma unroll
  for (int i = 0; i < N; ++i)
#pragma unroll
    for (int j = 0; j < 4; ++j) asm volatile("" : "+f"(d[i][j])::"memory");
}


// The same for register fragments (a wgmma's A operand from registers).
template <int N>
__device__ __forceinline__ void pin(unsigned (&a)[N][4]) {
#pragma unroll
  for (int i = 0; i < N; ++i)
#pragma unroll
    for (int j = 0; j < 4; ++j) asm volatile("" : "+r"(a[i][j])::"memory");
}

// The accumulator operands of a wgmma (d[i][0..3] for each n8 block i), in PTX operand order.
#define EPONA_WGMMA_BLOCK(d, i) "+f"(d[i][0]), "+f"(d[i][1]), "+f"(d[i][2]), "+f"(d[i][3])
#define EPONA_WGMMA_ACCUMULATORS_4(d) \
  EPONA_WGMMA_BLOCK(d, 0), EPONA_WGMMA_BLOCK(d, 1), EPONA_WGMMA_BLOCK(d, 2), EPONA_WGMMA_BLOCK(d, 3)
#define EPONA_WGMMA_ACCUMULATORS_8(d) \
  EPONA_WGMMA_ACCUMULATORS_4(d), EPONA_WGMMA_BLOCK(d, 4), EPONA_WGMMA_BLOCK(d, 5), EPONA_WGMMA_BLOCK(d, 6), \
      EPONA_WGMMA_BLOCK(d, 7)
#define EPONA_WGMMA_ACCUMULATORS_16(d)                                                                 \
  EPONA_WGMMA_ACCUMULATORS_8(d), EPONA_WGMMA_BLOCK(d, 8), EPONA_WGMMA_BLOCK(d, 9), EPONA_WGMMA_BLOCK(d, 10), \
      EPONA_WGMMA_BLOCK(d, 11), EPONA_WGMMA_BLOCK(d, 12), EPONA_WGMMA_BLOCK(d, 13), EPONA_WGMMA_BLOCK(d, 14), \
      EPONA_WGMMA_BLOCK(d, 15)

#define EPONA_WGMMA_ACCUMULATORS_32(d)                                                                      \
  EPONA_WGMMA_ACCUMULATORS_16(d), EPONA_WGMMA_BLOCK(d, 16), EPONA_WGMMA_BLOCK(d, 17), EPONA_WGMMA_BLOCK(d, 18),  \
      EPONA_WGMMA_BLOCK(d, 19), EPONA_WGMMA_BLOCK(d, 20), EPONA_WGMMA_BLOCK(d, 21), EPONA_WGMMA_BLOCK(d, 22),     \
      EPONA_WGMMA_BLOCK(d, 23), EPONA_WGMMA_BLOCK(d, 24), EPONA_WGMMA_BLOCK(d, 25), EPONA_WGMMA_BLOCK(d, 26),     \
      EPONA_WGMMA_BLOCK(d, 27), EPONA_WGMMA_BLOCK(d, 28), EPONA_WGMMA_BLOCK(d, 29), EPONA_WGMMA_BLOCK(d, 30),     \
      EPONA_WGMMA_BLOCK(d, 31)

// d (64 x N float32 in the accumulator layout: per warp 16 rows, d[i] = the n8 block i as
// mma.sync's C fragment) (+)= A (64 x 16, shared, descriptor a) B (16 x N, shared, descriptor b).
// accumulate = 0: d = A B.
__device__ __forceinline__ void wgmma_ss(float (&d)[4][4], std::uint64_t a, std::uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %18, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n32k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15}, %16, %17, p, 1, 1, 0, 0;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_4(d)
      : "l"(a), "l"(b), "r"(accumulate));
}

__device__ __forceinline__ void wgmma_ss(float (&d)[8][4], std::uint64_t a, std::uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %34, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n64k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31}, %32, %33, p, 1, 1, 0, 0;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_8(d)
      : "l"(a), "l"(b), "r"(accumulate));
}

__device__ __forceinline__ void wgmma_ss(float (&d)[16][4], std::uint64_t a, std::uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %66, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n128k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, %32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, %48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}, %64, %65, p, 1, 1, 0, 0;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_16(d)
      : "l"(a), "l"(b), "r"(accumulate));
}

__device__ __forceinline__ void wgmma_ss(float (&d)[32][4], std::uint64_t a, std::uint64_t b, int accumulate) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %130, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n256k16.f32.bf16.bf16 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, %32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, %48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63, %64, %65, %66, %67, %68, %69, %70, %71, %72, %73, %74, %75, %76, %77, %78, %79, %80, %81, %82, %83, %84, %85, %86, %87, %88, %89, %90, %91, %92, %93, %94, %95, %96, %97, %98, %99, %100, %101, %102, %103, %104, %105, %106, %107, %108, %109, %110, %111, %112, %113, %114, %115, %116, %117, %118, %119, %120, %121, %122, %123, %124, %125, %126, %127}, %128, %129, p, 1, 1, 0, 0;\n}\n"
      :
      EPONA_WGMMA_ACCUMULATORS_32(d)
      : "l"(a), "l"(b), "r"(accumulate));
}

namespace mbar {
__device__ __forceinline__ void init(unsigned bar, unsigned count) {
  asm volatile("mbarrier.init.shared::cta.b64 [%0], %1;\n" ::"r"(bar), "r"(count) : "memory");
}
__device__ __forceinline__ void expect_bytes(unsigned bar, unsigned bytes) {
  asm volatile("mbarrier.arrive.expect_tx.shared::cta.b64 _, [%0], %1;\n" ::"r"(bar), "r"(bytes) : "memory");
}
__device__ __forceinline__ void arrive(unsigned bar) {
  asm volatile("mbarrier.arrive.shared::cta.b64 _, [%0];\n" ::"r"(bar) : "memory");
}
// Waits until the phase of parity `parity` has completed (on a fresh barrier, parity 1 has).
__device__ __forceinline__ void wait(unsigned bar, unsigned parity) {
  unsigned done = 0;
  do {
    asm volatile(
        "{\n.reg .pred p;\nmbarrier.try_wait.parity.shared::cta.b64 p, [%1], %2;\nselp.u32 %0, 1, 0, p;\n}\n"
        : "=r"(done)
        : "r"(bar), "r"(parity)
        : "memory");
  } while (!done);
}
}  // namespace mbar

// wgmma groups still in flight may be at most N (N = 0: all done).
template <int N>
__device__ __forceinline__ void wgmma_wait() {
  asm volatile("wgmma.wait_group.sync.aligned %0;\n" ::"n"(N) : "memory");
}

// One 2-D box (inner coordinate c0, outer c1) of a tensor map into shared memory at dst,
// completing `bar`'s transaction count.
__device__ __forceinline__ void tma_load_2d(unsigned dst, const CUtensorMap& map, int c0, int c1, unsigned bar) {
  asm volatile(
      "cp.async.bulk.tensor.2d.shared::cluster.global.tile.mbarrier::complete_tx::bytes [%0], [%1, {%2, %3}], [%4];\n" ::"r"(dst),
      "l"(reinterpret_cast<std::uint64_t>(&map)), "r"(c0), "r"(c1), "r"(bar)
      : "memory");
}

// One 2-D box of shared memory at src to a tensor map's box at (c0, c1), as a bulk group of
// this thread (elements outside the tensor are not written).
__device__ __forceinline__ void tma_store_2d(const CUtensorMap& map, int c0, int c1, unsigned src) {
  asm volatile("cp.async.bulk.tensor.2d.global.shared::cta.bulk_group [%0, {%1, %2}], [%3];\n" ::"l"(
                   reinterpret_cast<std::uint64_t>(&map)),
               "r"(c0), "r"(c1), "r"(src)
               : "memory");
}
__device__ __forceinline__ void bulk_commit() { asm volatile("cp.async.bulk.commit_group;\n" ::: "memory"); }
// This thread's bulk stores have finished reading shared memory (Read) or are complete.
template <bool Read>
__device__ __forceinline__ void bulk_wait_all() {
  if constexpr (Read) asm volatile("cp.async.bulk.wait_group.read 0;\n" ::: "memory");
  else asm volatile("cp.async.bulk.wait_group 0;\n" ::: "memory");
}

// The driver's cuTensorMapEncodeTiled, fetched once through the runtime (no libcuda link); null
// where the driver lacks it.
using TensorMapEncoder = CUresult (*)(CUtensorMap*, CUtensorMapDataType, cuuint32_t, void*, const cuuint64_t*,
                                      const cuuint64_t*, const cuuint32_t*, const cuuint32_t*, CUtensorMapInterleave,
                                      CUtensorMapSwizzle, CUtensorMapL2promotion, CUtensorMapFloatOOBfill);
inline TensorMapEncoder tensor_map_encoder() {
  static const TensorMapEncoder encode = [] {
    void* fn = nullptr;
    cudaDriverEntryPointQueryResult found{};
    if (cudaGetDriverEntryPointByVersion("cuTensorMapEncodeTiled", &fn, 12000, cudaEnableDefault, &found) !=
            cudaSuccess ||
        found != cudaDriverEntryPointSuccess) {
      (void)cudaGetLastError();
      return TensorMapEncoder{};
    }
    return reinterpret_cast<TensorMapEncoder>(fn);
  }();
  return encode;
}

}  // namespace epona::cuda::detail
