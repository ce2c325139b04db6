// epona/nn/backend_context.hpp — what layer code needs to know about a backend: its kernel
// context type, its GEMM epilogue enum, and how host-side parameters and tables reach its
// memory. Specialised here for the CPU; the CUDA backend specialises BackendTraits<Cuda>.
#pragma once

#include <cstring>

#include "epona/core/backend.hpp"
#include "epona/core/tensor.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/ops.hpp"
#include "epona/nn/cpu_extra_ops.hpp"

namespace epona {

template <class B> struct BackendTraits;

template <> struct BackendTraits<Cpu> {
  using Context = cpu::Context;
  using Epilogue = cpu::Epilogue;
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

template <class B> using BackendContext = typename BackendTraits<B>::Context;
template <class B> using BackendEpilogue = typename BackendTraits<B>::Epilogue;

}  // namespace epona
