// epona/cuda/runtime/memory.hpp — device memory for Tensor<T, Cuda>: the Cuda backend tag, plain
// cudaMalloc allocations owned through shared_ptr, host <-> device copies ordered on a
// context's stream, and a bump arena so steady-state loops allocate nothing.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <memory>

#include "epona/core/backend.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"

namespace epona {

struct Cuda {
  static constexpr const char* name = "cuda";
};

template <> struct BackendMemory<Cuda> {
  static constexpr std::size_t alignment = 256;  // what cudaMalloc guarantees
  static std::shared_ptr<void> allocate(std::size_t bytes) {
    if (bytes == 0) bytes = alignment;
    void* p = nullptr;
    const cudaError_t status = cudaMalloc(&p, bytes);
    if (status != cudaSuccess) {
      (void)cudaGetLastError();
      fail("out of device memory: cannot allocate ", bytes, " bytes (", cudaGetErrorString(status), ")");
    }
    // A deleter must not throw; a failing cudaFree at exit has nothing left to report to.
    return std::shared_ptr<void>(p, [](void* q) { cudaFree(q); });
  }
  static constexpr bool host_accessible = false;
};

}  // namespace epona

namespace epona::cuda {

template <class T> using DeviceTensor = Tensor<T, Cuda>;

namespace detail {
template <class T, class B1, class B2>
void check_same_shape(const Tensor<T, B1>& dst, const Tensor<T, B2>& src, const char* what) {
  EPONA_CHECK(dst.shape() == src.shape(), what, ": destination ", shape_str(dst.shape()), " and source ",
              shape_str(src.shape()), " differ");
}
}  // namespace detail

// Host -> device, ordered on ctx's stream. Returns once the host buffer may be reused.
template <class T>
void copy(Context& ctx, Tensor<T, Cuda>& dst, const Tensor<T, Cpu>& src) {
  detail::check_same_shape(dst, src, "copy to device");
  if (!src.numel()) return;
  EPONA_CUDA_CHECK(cudaMemcpyAsync(dst.data(), src.data(), src.nbytes(), cudaMemcpyHostToDevice, ctx.stream()));
  ctx.synchronize();
}

// Host -> device, ordered on ctx's stream, without waiting for the stream where the context's
// pinned ring takes the bytes (Context::upload_staged); otherwise as copy() above. The host
// buffer may be reused on return either way.
template <class T>
void copy_async(Context& ctx, Tensor<T, Cuda>& dst, const Tensor<T, Cpu>& src) {
  detail::check_same_shape(dst, src, "copy to device");
  if (!ctx.upload_staged(dst.data(), src.data(), src.nbytes())) copy(ctx, dst, src);
}

// Device -> host, ordered after all work queued on ctx's stream.
template <class T>
void copy(Context& ctx, Tensor<T, Cpu>& dst, const Tensor<T, Cuda>& src) {
  detail::check_same_shape(dst, src, "copy to host");
  if (!src.numel()) return;
  EPONA_CUDA_CHECK(cudaMemcpyAsync(dst.data(), src.data(), src.nbytes(), cudaMemcpyDeviceToHost, ctx.stream()));
  ctx.synchronize();
}

// Device -> device, asynchronous on ctx's stream.
template <class T>
void copy(Context& ctx, Tensor<T, Cuda>& dst, const Tensor<T, Cuda>& src) {
  detail::check_same_shape(dst, src, "device copy");
  if (!src.numel()) return;
  EPONA_CUDA_CHECK(
      cudaMemcpyAsync(dst.data(), src.data(), src.nbytes(), cudaMemcpyDeviceToDevice, ctx.stream()));
}

template <class T>
Tensor<T, Cuda> to_device(Context& ctx, const Tensor<T, Cpu>& src) {
  Tensor<T, Cuda> dst(src.shape());
  copy(ctx, dst, src);
  return dst;
}

template <class T>
Tensor<T, Cpu> to_host(Context& ctx, const Tensor<T, Cuda>& src) {
  Tensor<T, Cpu> dst(src.shape());
  copy(ctx, dst, src);
  return dst;
}

// Sets every byte of a device tensor (asynchronous). 0xFF bytes are NaN in float32 and
// bfloat16: tests poison outputs with it so that unwritten elements show.
template <class T>
void fill_bytes(Context& ctx, Tensor<T, Cuda>& t, unsigned char byte) {
  if (t.numel()) EPONA_CUDA_CHECK(cudaMemsetAsync(t.data(), byte, t.nbytes(), ctx.stream()));
}

// One device allocation handed out front to back. Tensors from the arena are views: they
// stay valid until reset()/rewind() past them or the arena's destruction, whichever is
// first (each view also holds the block alive, so destruction alone never dangles).
class DeviceArena {
 public:
  static constexpr std::size_t alignment = 256;  // keeps every tensor ready for 16-byte vector and cuBLASLt access

  explicit DeviceArena(std::size_t bytes) : block_(BackendMemory<Cuda>::allocate(bytes)), capacity_(bytes) {}

  template <class T>
  Tensor<T, Cuda> alloc(Shape shape) {
    const auto bytes = static_cast<std::size_t>(shape_numel(shape)) * sizeof(T);
    const std::size_t begin = round_up(used_);
    EPONA_CHECK(begin <= capacity_ && bytes <= capacity_ - begin, "device arena exhausted: ", shape_str(shape),
                " needs ", bytes, " bytes, ", capacity_ - std::min(begin, capacity_), " of ", capacity_, " left");
    used_ = begin + bytes;
    peak_ = std::max(peak_, used_);
    auto* p = reinterpret_cast<T*>(static_cast<unsigned char*>(block_.get()) + begin);
    return Tensor<T, Cuda>::view(p, std::move(shape), block_);
  }

  std::size_t mark() const { return used_; }
  void rewind(std::size_t mark) {
    EPONA_CHECK(mark <= used_, "device arena: rewind to ", mark, " beyond the ", used_, " bytes in use");
    used_ = mark;
  }
  void reset() { used_ = 0; }
  std::size_t used() const { return used_; }
  std::size_t peak() const { return peak_; }
  std::size_t capacity() const { return capacity_; }

 private:
  static std::size_t round_up(std::size_t n) { return (n + alignment - 1) / alignment * alignment; }

  std::shared_ptr<void> block_;
  std::size_t capacity_ = 0, used_ = 0, peak_ = 0;
};

}  // namespace epona::cuda
