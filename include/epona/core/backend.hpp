// epona/core/backend.hpp — backend tags. Model code is templated on a backend tag; each
// backend provides memory (BackendMemory<B>) and its kernels as free functions in its own
// namespace (epona::cpu, epona::cuda) that take that backend's Context first, so layer
// code calls them unqualified and argument-dependent lookup picks the backend.
#pragma once

#include <cstddef>
#include <cstdlib>
#include <memory>
#include <new>

#include "epona/core/error.hpp"

namespace epona {

struct Cpu;   // host memory, Eigen + xsimd kernels (epona/cpu/)
struct Cuda;  // device memory, cuBLASLt + own kernels (epona/cuda/, needs nvcc)

// Allocation of raw bytes on a backend. Specialised per backend; the CUDA one lives in
// epona/cuda/runtime/memory.hpp so that host-only builds never see CUDA headers.
template <class B> struct BackendMemory;

template <> struct BackendMemory<Cpu> {
  static constexpr std::size_t alignment = 64;  // a cache line, and a full AVX-512 register
  static std::shared_ptr<void> allocate(std::size_t bytes) {
    if (bytes == 0) bytes = alignment;
    void* p = ::operator new(bytes, std::align_val_t{alignment}, std::nothrow);
    EPONA_CHECK(p != nullptr, "out of host memory: cannot allocate ", bytes, " bytes");
    return std::shared_ptr<void>(p, [](void* q) { ::operator delete(q, std::align_val_t{alignment}); });
  }
  static constexpr bool host_accessible = true;
};

template <class B> inline constexpr bool is_host_backend = BackendMemory<B>::host_accessible;

}  // namespace epona
