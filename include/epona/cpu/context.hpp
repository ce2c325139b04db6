// epona/cpu/context.hpp — the CPU backend's execution context: thread count for the
// kernels (OpenMP) and Eigen's GEMM. Every CPU kernel takes it first, so layer code calls
// kernels unqualified and argument-dependent lookup picks this backend.
#pragma once

#include <algorithm>
#include <thread>

// GCC 12 flags its own _mm512_undefined_* intrinsics as uninitialised wherever Eigen's
// AVX-512 GEMM packing inlines them (a known false positive); silenced for Eigen only.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#endif
#include <Eigen/Core>
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
#if defined(_OPENMP)
#include <omp.h>
#endif

#include "epona/core/backend.hpp"
#include "epona/core/tensor.hpp"

namespace epona {
struct Cpu {
  static constexpr const char* name = "cpu";
};
}  // namespace epona

namespace epona::cpu {

class Context {
 public:
  // threads <= 0: all hardware threads.
  explicit Context(int threads = 0) { set_threads(threads); }

  void set_threads(int threads) {
    const int hw = std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
    threads_ = threads > 0 ? threads : hw;
    Eigen::setNbThreads(threads_);
#if defined(_OPENMP)
    omp_set_num_threads(threads_);
#endif
  }
  int threads() const { return threads_; }

 private:
  int threads_ = 1;
};

template <class T> using HostTensor = Tensor<T, Cpu>;

}  // namespace epona::cpu
