// epona/cuda/ops.cuh — umbrella for the CUDA backend's kernels (include from .cu files only;
// host-only builds never see CUDA headers).
#pragma once

#include "epona/cuda/pointwise/activation.cuh"
#include "epona/cuda/attention/attention.cuh"
#include "epona/cuda/attention/short_attention_qk_layer_norm.cuh"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/pointwise/elementwise.cuh"
#include "epona/cuda/pointwise/frame_tokens.cuh"
#include "epona/cuda/gemm/gemm.cuh"
#include "epona/cuda/runtime/memory.hpp"
#include "epona/cuda/pointwise/norm.cuh"
#include "epona/cuda/attention/qk_layer_norm_rope.cuh"
#include "epona/cuda/attention/rope.cuh"
