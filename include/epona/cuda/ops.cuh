// epona/cuda/ops.cuh — umbrella for the CUDA backend's kernels (include from .cu files only;
// host-only builds never see CUDA headers).
#pragma once

#include "epona/cuda/activation.cuh"
#include "epona/cuda/attention.cuh"
#include "epona/cuda/attention_qk_norm.cuh"
#include "epona/cuda/check.hpp"
#include "epona/cuda/context.hpp"
#include "epona/cuda/elementwise.cuh"
#include "epona/cuda/frame_tokens.cuh"
#include "epona/cuda/gemm.cuh"
#include "epona/cuda/memory.hpp"
#include "epona/cuda/norm.cuh"
#include "epona/cuda/qk_layer_norm_rope.cuh"
#include "epona/cuda/rope.cuh"
