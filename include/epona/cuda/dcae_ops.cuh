// epona/cuda/dcae_ops.cuh — everything the DC-AE (model/dcae.hpp) needs from the CUDA backend,
// in one include: the phase-1 kernels (linear, attention, RoPE, norms, residuals), the
// channels-last convolution/norm/LiteMLA/shuffle kernels (BatchNorm folding into convs), the
// fused temporal blocks, scratch memory, BackendTraits<Cuda>.
#pragma once

#include "epona/cuda/backend.cuh"
#include "epona/cuda/conv.cuh"
#include "epona/cuda/conv_fold.cuh"
#include "epona/cuda/dcae_temporal.cuh"
#include "epona/cuda/lite_mla.cuh"
#include "epona/cuda/norm2d.cuh"
#include "epona/cuda/ops.cuh"
#include "epona/cuda/pixel_shuffle.cuh"
#include "epona/cuda/scratch.hpp"
