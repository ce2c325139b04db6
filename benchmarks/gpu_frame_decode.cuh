// benchmarks/gpu_frame_decode.cuh — one frame's DC-AE decode as the epona program's FrameDecoder runs
// it beside the next step (apps/epona/rollout_common.hpp), for the rollout rows of bench_gpu_world
// and bench_gpu_shards: the real DC-AE with random weights, on a context and stream of its own on
// the GPU current where it is made, the picture brought back to the host.
#pragma once

#include <cstdint>

#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"
#include "epona/cuda/runtime/check.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/world_model.hpp"

namespace epona::bench {

template <class W>
class FrameDecode {
 public:
  explicit FrameDecode(const WorldModelConfig& w) : latent_h_(w.latent_h()), latent_w_(w.latent_w()) {
    dcae_.randomize(1);
  }
  // The picture of one frame's latent tokens; callable from a worker thread (it takes the GPU of its
  // context first).
  Tensor<float> operator()(const Tensor<float>& tokens) {
    EPONA_CUDA_CHECK(cudaSetDevice(ctx_.info().device));
    const Tensor<float> z = tokens_to_latent(host_, tokens, latent_h_, latent_w_);
    const Tensor<float, Cuda> images = dcae_.decode(ctx_, BackendTraits<Cuda>::upload(z), false);
    Tensor<float> out(images.shape());
    BackendTraits<Cuda>::download_into(ctx_, images, out);
    return out;
  }

 private:
  Dcae<Cuda, W> dcae_{DcaeConfig{}};
  cuda::Context ctx_;
  cpu::Context host_;
  std::int64_t latent_h_, latent_w_;
};

}  // namespace epona::bench
