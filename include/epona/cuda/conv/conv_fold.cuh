// epona/cuda/conv/conv_fold.cuh — folds an eval-mode BatchNorm2d into the convolution before it
// (conv -> BN becomes one conv with per-output-channel scaled weights and a bias), so a DC-AE
// ResBlock's conv2 -> BN -> + x runs as one fused cuDNN call (conv2d_residual). Made at bind time.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>

#include "epona/core/tensor.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/conv/conv.cuh"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/runtime/kernel_policy.hpp"
#include "epona/cuda/runtime/memory.hpp"

namespace epona {

namespace cuda::conv_detail {

// w'[o, ...] = w[o, ...] · s[o], b'[o] = beta[o] - mean[o] · s[o] with s = gamma / sqrt(var + eps):
// the scale in float64, each product rounded once to T.
template <class T>
__global__ void fold_batch_norm_kernel(const T* __restrict__ w, const float* __restrict__ gamma,
                                       const float* __restrict__ beta, const float* __restrict__ mean,
                                       const float* __restrict__ var, double eps, T* __restrict__ w_out,
                                       T* __restrict__ b_out, std::int64_t out_channels, std::int64_t per_out) {
  const std::int64_t n = out_channels * per_out;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < n;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const std::int64_t o = i / per_out;
    const double scale = double(gamma[o]) / sqrt(double(var[o]) + eps);
    w_out[i] = detail::from_f32<T>(static_cast<float>(double(detail::to_f32(w[i])) * scale));
    if (i % per_out == 0) b_out[o] = detail::from_f32<T>(static_cast<float>(double(beta[o]) - double(mean[o]) * scale));
  }
}

}  // namespace cuda::conv_detail

// The conv weight `weight` [O, ...] (no bias) followed by BatchNorm2d(O) in eval mode (gamma,
// beta, running mean/var, eps) as one conv: folded_weight (same shape) and folded_bias [O] in T.
// Found by nn::ResBlock through argument-dependent lookup. False, leaving the outputs alone, when
// the fused epilogues are off (EPONA_CUDA_CONV_FUSE=0: the block keeps conv -> norm_2d_add).
// Synchronous (runs while weights are bound, before any model context exists): the policy is
// the environment's unless the caller passes one (tests); folded or not, the block is exact.
template <class T>
bool fold_batch_norm(const Tensor<T, Cuda>& weight, const Tensor<float, Cuda>& gamma, const Tensor<float, Cuda>& beta,
                     const Tensor<float, Cuda>& mean, const Tensor<float, Cuda>& var, float eps,
                     Tensor<T, Cuda>& folded_weight, Tensor<T, Cuda>& folded_bias,
                     const cuda::KernelPolicy& policy = cuda::KernelPolicy::from_environment()) {
  if (!policy.conv_fusion) return false;
  EPONA_CHECK(weight.dim() >= 1 && weight.numel() > 0, "fold_batch_norm: empty conv weight");
  const std::int64_t O = weight.size(0);
  for (const auto* t : {&gamma, &beta, &mean, &var})
    EPONA_CHECK(t->numel() == O, "fold_batch_norm: BatchNorm parameters of ", t->numel(), " values for ", O,
                " output channels");
  // run on the device holding the weights, restoring the caller's current device after
  cudaPointerAttributes attr{};
  EPONA_CUDA_CHECK(cudaPointerGetAttributes(&attr, weight.data()));
  int previous = 0;
  EPONA_CUDA_CHECK(cudaGetDevice(&previous));
  EPONA_CUDA_CHECK(cudaSetDevice(attr.device));
  Tensor<T, Cuda> w(weight.shape()), b({O});
  const std::int64_t n = weight.numel();
  const unsigned blocks = static_cast<unsigned>(std::min<std::int64_t>((n + 255) / 256, 65535));
  cuda::conv_detail::fold_batch_norm_kernel<<<blocks, 256>>>(weight.data(), gamma.data(), beta.data(), mean.data(),
                                                              var.data(), double(eps), w.data(), b.data(), O, n / O);
  EPONA_CUDA_CHECK(cudaGetLastError());
  EPONA_CUDA_CHECK(cudaDeviceSynchronize());
  EPONA_CUDA_CHECK(cudaSetDevice(previous));
  folded_weight = std::move(w);
  folded_bias = std::move(b);
  return true;
}

}  // namespace epona
