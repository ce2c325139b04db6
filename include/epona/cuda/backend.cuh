// epona/cuda/backend.cuh — the CUDA backend as the model templates see it: BackendTraits<Cuda>
// (context, epilogue/attention types, bf16 or float32 activations = the weight type, weight
// upload at bind time, host <-> arena copies, CUDA-graph replay) and every kernel the layers
// call unqualified. Include it (from a .cu file) before instantiating a model on Cuda.
#pragma once

#include "epona/core/backend_capabilities.hpp"
#include "epona/core/backend_traits.hpp"
#include "epona/cuda/runtime/graph.hpp"
#include "epona/cuda/runtime/memory.hpp"
#include "epona/cuda/ops.cuh"
#include "epona/cuda/attention/qk_rms_norm_rope.cuh"
#include "epona/cuda/runtime/side_stream.hpp"
#include "epona/cuda/pointwise/copy_convert_axpy.cuh"

namespace epona {

template <> struct BackendTraits<Cuda> {
  using Context = cuda::Context;
  using Epilogue = cuda::Epilogue;
  using AttentionShape = cuda::AttentionShape;
  using Mask = cuda::Mask;
  using GraphCache = cuda::GraphCache;
  using SideQueue = cuda::SideStream;
  // bf16 weights: bf16 activations (GEMM inputs/outputs, attention), float32 inside kernels;
  // float32 weights: float32 everywhere. The MST residual stream is float32 in both.
  template <class W> using Activation = W;

  // Device copy of a host tensor (an empty tensor stays empty). Synchronous: the host
  // tensor may be released on return.
  template <class T>
  static Tensor<T, Cuda> upload(const Tensor<T, Cpu>& host) {
    if (host.empty()) return {};
    return cuda::to_device(uploader(), host);
  }
  template <class T>
  static void upload_into(Context& ctx, const Tensor<T, Cpu>& host, Tensor<T, Cuda>& dst) {
    EPONA_CHECK(host.numel() == dst.numel(), "upload_into: ", shape_str(host.shape()), " into ",
                shape_str(dst.shape()));
    auto view = Tensor<T, Cuda>::view(dst.data(), host.shape(), dst.storage());
    cuda::copy_async(ctx, view, host);  // the model's uploads do not wait for the stream
  }
  template <class T>
  static void download_into(Context& ctx, const Tensor<T, Cuda>& src, Tensor<T, Cpu>& host) {
    EPONA_CHECK(host.numel() == src.numel(), "download_into: ", shape_str(src.shape()), " into ",
                shape_str(host.shape()));
    auto view = Tensor<T, Cpu>::view(host.data(), src.shape(), host.storage());
    cuda::copy(ctx, view, src);
  }

 private:
  // Weights are uploaded while binding, before any model context exists: a context of its own
  // (device 0) orders those copies.
  static cuda::Context& uploader() {
    static cuda::Context ctx(0, 0);
    return ctx;
  }
};

template <> struct BackendOf<cuda::Context> { using type = Cuda; };

// The CUDA backend has every optional fused kernel of the contract (core/backend_capabilities.hpp),
// for both activation types: a kernel whose signature drifts fails here, not as a silent
// fallback to the composed passes.
template <class A>
constexpr bool cuda_has_every_capability() {
  using C = cuda::Context;
  static_assert(AddGatedNormFromInput<C, A>, "CUDA backend lacks capability AddGatedNormFromInput");
  static_assert(JointQkNormRope<C, A>, "CUDA backend lacks capability JointQkNormRope");
  static_assert(ResidualGemm<C, A>, "CUDA backend lacks capability ResidualGemm");
  static_assert(ShortAttentionQkNorm<C, A>, "CUDA backend lacks capability ShortAttentionQkNorm");
  static_assert(FusedFrameTokens<C, A>, "CUDA backend lacks capability FusedFrameTokens");
  static_assert(QkLayerNormRope<C, A>, "CUDA backend lacks capability QkLayerNormRope");
  static_assert(PairedGemm<C>, "CUDA backend lacks capability PairedGemm");
  static_assert(GroupedLinear<C, A>, "CUDA backend lacks capability GroupedLinear");
  static_assert(ItemRowNorms<C, A>, "CUDA backend lacks capability ItemRowNorms");
  return true;
}
static_assert(cuda_has_every_capability<float>() && cuda_has_every_capability<bf16>());

}  // namespace epona
