// epona/cuda/dcae_ops.cuh — everything the DC-AE (model/dcae.hpp) needs from the CUDA backend,
// in one include: the phase-1 kernels (linear, attention, RoPE, norms, residuals), the
// channels-last convolution/norm/LiteMLA/shuffle kernels (BatchNorm folding into convs), the
// fused temporal blocks, scratch memory, BackendTraits<Cuda>.
#pragma once

#include "epona/cuda/backend.cuh"
#include "epona/cuda/conv/conv.cuh"
#include "epona/cuda/conv/conv_fold.cuh"
#include "epona/cuda/conv/dcae_temporal.cuh"
#include "epona/cuda/attention/lite_mla.cuh"
#include "epona/cuda/pointwise/norm2d.cuh"
#include "epona/cuda/ops.cuh"
#include "epona/cuda/pointwise/pixel_shuffle.cuh"
#include "epona/cuda/runtime/scratch.hpp"
