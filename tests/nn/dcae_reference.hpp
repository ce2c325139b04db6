// The DC-AE layer tests' float64 references (docs/dcae.md §3-§6): the per-op loops of
// tests/ops/reference.hpp under the name dcae_ref, with reference_common's helpers.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "epona/core/tensor.hpp"
#include "../ops/reference.hpp"
#include "reference_common.hpp"

namespace dcae_ref {

using namespace reference_common;  // Vec, i64, HostTensor, random_tensor, to_vec, rel_max

// The per-op references, written once in tests/ops/reference.hpp.
using ops_ref::average_shortcut;
using ops_ref::conv2d;
using ops_ref::duplicate_shortcut;
using ops_ref::relu;
using ops_ref::relu_linear_attention;
using ops_ref::rms_norm_2d;
using ops_ref::shuffle;
using ops_ref::silu;
using ops_ref::unshuffle;

}  // namespace dcae_ref
