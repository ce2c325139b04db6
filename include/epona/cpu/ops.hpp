// epona/cpu/ops.hpp — umbrella for the CPU backend's kernels.
#pragma once

#include "epona/cpu/activation.hpp"
#include "epona/cpu/attention.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/elementwise.hpp"
#include "epona/cpu/gemm.hpp"
#include "epona/cpu/norm.hpp"
#include "epona/cpu/rope.hpp"
#include "epona/cpu/simd.hpp"
#include "epona/cpu/softmax.hpp"
