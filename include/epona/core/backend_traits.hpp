// epona/core/backend_traits.hpp — the backend-neutral half of what layer code knows about a
// backend: BackendTraits<B> (its kernel context, epilogue and attention types, activation type,
// host <-> backend copies, graph replay), declared here and specialised by each backend —
// nn/backend_context.hpp for the CPU, cuda/backend.cuh for CUDA — and the helpers written on
// top of it. Below both backends so that cuda/ specialises it without including nn/.
#pragma once

#include <cstdint>
#include <type_traits>
#include <vector>

#include "epona/core/backend.hpp"
#include "epona/core/tensor.hpp"

namespace epona {

template <class B> struct BackendTraits;

// Identity of a recorded piece of work: the buffers and sizes it was recorded with.
using GraphKey = std::vector<std::uint64_t>;

// The backend whose kernels take a given context type (layer helpers that only see a context).
template <class Context> struct BackendOf;

template <class B> using BackendContext = typename BackendTraits<B>::Context;
template <class B> using BackendEpilogue = typename BackendTraits<B>::Epilogue;
// Storage type of the activations of a layer with weights W on backend B: float on the CPU;
// on the GPU the weight type (bf16 GEMMs read and write bf16, as PyTorch's autocast).
template <class B, class W> using Activation = typename BackendTraits<B>::template Activation<W>;

// A backend tensor's values in host memory: the tensor itself on a host backend, else a copy
// (synchronous: the context's queued work finishes first).
template <class B, class T>
Tensor<T, Cpu> host_tensor(BackendContext<B>& ctx, const Tensor<T, B>& t) {
  if constexpr (is_host_backend<B>) {
    return t;
  } else {
    Tensor<T, Cpu> host(t.shape());
    BackendTraits<B>::download_into(ctx, t, host);
    return host;
  }
}

// A host tensor converted element by element to T (bf16 rounds to nearest even).
template <class T>
Tensor<T, Cpu> host_as(const Tensor<float, Cpu>& src) {
  if constexpr (std::is_same_v<T, float>) {
    return src;
  } else {
    Tensor<T, Cpu> out(src.shape());
    for (std::int64_t i = 0; i < src.numel(); ++i) out.data()[i] = T(src.data()[i]);
    return out;
  }
}

// Uploads a float host tensor into a backend tensor of T (converted on the host).
template <class B, class T>
void upload_as(BackendContext<B>& ctx, const Tensor<float, Cpu>& host, Tensor<T, B>& dst) {
  BackendTraits<B>::upload_into(ctx, host_as<T>(host), dst);
}

}  // namespace epona
