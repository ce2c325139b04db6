// epona/nn/backend_context.hpp — what layer code needs to know about a backend: its kernel
// context, GEMM epilogue and attention-layout types, the activation storage type for a weight
// type, how host tensors reach its memory, and how a loop of kernels is replayed (a CUDA graph,
// or just run). BackendTraits and the helpers over it are declared in core/backend_traits.hpp;
// specialised here for the CPU, and in epona/cuda/backend.cuh for CUDA.
#pragma once

#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#include "epona/core/backend.hpp"
#include "epona/core/backend_traits.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/copy_fill_axpy.hpp"
#include "epona/cpu/ops.hpp"
#include "epona/cpu/qk_rms_norm_rope.hpp"
#include "epona/cpu/residual_norm.hpp"

namespace epona {

// The CPU has no launch overhead to save: work is simply run.
struct ImmediateGraphCache {
  template <class Context, class Work>
  void run(Context&, const GraphKey&, Work&& work) {
    work();
  }
};

// Work split over two queues that may run concurrently (the two streams of a DiT double
// block): on the CPU both queues are the one context and everything runs in order.
struct InOrderQueues {
  template <class Context>
  Context& side(Context& main) {
    return main;
  }
  template <class Context>
  void fork(Context&) {}
  template <class Context>
  void join(Context&) {}
};

template <> struct BackendTraits<Cpu> {
  using Context = cpu::Context;
  using Epilogue = cpu::Epilogue;
  using AttentionShape = cpu::AttentionShape;
  using Mask = cpu::Mask;
  using GraphCache = ImmediateGraphCache;
  using SideQueue = InOrderQueues;
  // Activations between layers: float32 on the CPU whatever the weights (bf16 weights are
  // widened inside the GEMM; everything else computes in float32).
  template <class W> using Activation = float;

  // A backend tensor holding a host tensor's values: host memory already is CPU memory.
  template <class T>
  static Tensor<T, Cpu> upload(const Tensor<T, Cpu>& host) { return host; }
  // Copies a host tensor into an existing backend tensor of the same size (arena buffers).
  template <class T>
  static void upload_into(Context&, const Tensor<T, Cpu>& host, Tensor<T, Cpu>& dst) {
    EPONA_CHECK(host.numel() == dst.numel(), "upload_into: ", shape_str(host.shape()), " into ",
                shape_str(dst.shape()));
    if (host.numel() && host.data() != dst.data()) std::memcpy(dst.data(), host.data(), host.nbytes());
  }
  // Copies a backend tensor into an existing host tensor of the same size.
  template <class T>
  static void download_into(Context&, const Tensor<T, Cpu>& src, Tensor<T, Cpu>& host) {
    EPONA_CHECK(host.numel() == src.numel(), "download_into: ", shape_str(src.shape()), " into ",
                shape_str(host.shape()));
    if (src.numel() && host.data() != src.data()) std::memcpy(host.data(), src.data(), src.nbytes());
  }
};

template <> struct BackendOf<cpu::Context> { using type = Cpu; };

}  // namespace epona
