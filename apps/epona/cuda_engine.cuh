// apps/epona/cuda_engine.cuh — builds the epona program's CUDA engine, ModelEngine<Cuda, float or
// bf16> (apps/epona/engine.hpp); included by cuda_engine.cu (the program's only nvcc unit) and by
// the GPU test of the engine, so both run the same construction.
#pragma once

#include <cstdlib>
#include <memory>

#include <numeric>
#include <vector>

#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"
#include "epona/cuda/runtime/peer_shard_sum.cuh"
#if defined(EPONA_APP_NCCL)
#include "epona/cuda/runtime/nccl_shard_sum.hpp"
#endif

#include "engine.hpp"

namespace epona::app {

namespace cuda_engine_detail {
// The cuDNN handles and plans are process-wide; released with the engine, not by a static
// destructor that runs after the CUDA context is gone (compute-sanitizer reported them leaked).
// --reproducible: no timed cuBLASLt candidates (which one wins can differ between runs) unless
// EPONA_CUDA_GEMM_TUNE asks for them.
template <class W>
void configure(ModelEngine<Cuda, W>& engine, const ComputeOptions& c, bool releases_cudnn) {
  if (releases_cudnn) engine.after_destruction(cuda::release_cudnn);
  if (c.reproducible && !std::getenv("EPONA_CUDA_GEMM_TUNE"))
    engine.configure_contexts([](cuda::Context& ctx) { ctx.policy().gemm_tuning = cuda::GemmTuning::Off; });
}

// The sharded engine over `group`'s GPUs (shard 0, on GPU 0, also holds the DC-AE and releases cuDNN).
template <class W, class Group>
std::unique_ptr<Engine> sharded_over(const ComputeOptions& c, std::unique_ptr<Group> group, const std::string& how) {
  auto engine = std::make_unique<ShardedEngine<Cuda, W, Group>>(c, std::move(group), "one per GPU, their sums through " + how);
  engine->each_shard([&](std::int64_t r, ModelEngine<Cuda, W>& e) { configure(e, c, r == 0); });
  return engine;
}

// --shard-sum auto: the peer group over two GPUs that reach each other's memory, where it measured
// faster (two H200s: VisDiT sample 190.8 against 230.6 ms through NCCL), and wherever this build
// has no NCCL; NCCL over more GPUs, where each GPU's part crosses NVLink once per other GPU (four
// H200s: 229.7 against 190.6 ms; docs/parallel.md).
inline bool peer_by_default(const std::vector<int>& devices) {
#if defined(EPONA_APP_NCCL)
  if (devices.size() > 2) return false;
#endif
  return !cuda::unreachable_peers(devices);
}

// --tensor-parallel N: the VisDiT over GPUs 0..N-1, its sums through the peer group or NCCL
// (--shard-sum; docs/parallel.md).
template <class W>
std::unique_ptr<Engine> build_sharded(const ComputeOptions& c) {
  int gpus = 0;
  EPONA_CUDA_CHECK(cudaGetDeviceCount(&gpus));
  EPONA_CHECK(c.shards <= gpus, "--tensor-parallel ", c.shards, " needs ", c.shards, " GPUs (one per shard); ", gpus,
              " visible");
  std::vector<int> devices(static_cast<std::size_t>(c.shards));
  std::iota(devices.begin(), devices.end(), 0);
  const bool peer = c.shard_sum == "peer" || (c.shard_sum == "auto" && peer_by_default(devices));
  const std::string picked = c.shard_sum == "auto" ? " (--shard-sum auto)" : "";
  if (peer) return sharded_over<W>(c, std::make_unique<cuda::PeerShardGroup<W>>(devices), "our peer kernel" + picked);
#if defined(EPONA_APP_NCCL)
  return sharded_over<W>(c, std::make_unique<cuda::NcclShardGroup<W>>(devices), "NCCL" + picked);
#else
  fail("--tensor-parallel ", c.shards, " with --backend cuda: ",
       c.shard_sum == "nccl" ? "--shard-sum nccl needs NCCL" : "these GPUs do not reach each other's memory, and NCCL",
       ", which this build of the program lacks (CMake finds it beside the CUDA toolkit; docs/parallel.md)");
#endif
}

template <class W>
std::unique_ptr<Engine> build(const ComputeOptions& c) {
  if (c.shards > 1) return build_sharded<W>(c);
  auto engine = std::make_unique<ModelEngine<Cuda, W>>(c);
  configure(*engine, c, true);
  return engine;
}
}  // namespace cuda_engine_detail

inline std::unique_ptr<Engine> build_cuda_engine(const ComputeOptions& c) {
  EPONA_CHECK(cuda::has_gpu(), "--backend cuda: no CUDA device is available (driver and GPU needed); use --backend cpu");
  return c.bf16_weights ? cuda_engine_detail::build<bf16>(c) : cuda_engine_detail::build<float>(c);
}

}  // namespace epona::app
