// epona/cuda/conv/dcae_fusion.hpp — the switch of the DC-AE's fused GPU kernels (the temporal blocks
// as one kernel per block, the upsampling pair's shuffle + shortcut in one pass, the decoder's
// last shuffle written straight into the NCHW image). On by default; EPONA_CUDA_DCAE_FUSE=0
// (read once) keeps the unfused kernels.
#pragma once

#include <atomic>

#include "epona/core/env.hpp"

namespace epona::cuda {

namespace dcae_fusion_detail {
inline std::atomic<bool>& flag() {
  static std::atomic<bool> on{env_flag("EPONA_CUDA_DCAE_FUSE", true)};
  return on;
}
}  // namespace dcae_fusion_detail

// Whether the DC-AE's fused kernels run (side-by-side timing and tests turn them off).
inline bool dcae_fusion() { return dcae_fusion_detail::flag().load(); }
inline void set_dcae_fusion(bool on) { dcae_fusion_detail::flag().store(on); }

}  // namespace epona::cuda
