// epona/cuda/runtime/device_shard_threads.hpp — what the tensor-parallel groups over the GPUs of
// one host share (nccl_shard_sum.hpp, peer_shard_sum.cuh): shard r on GPU devices[r], driven by host
// thread r of one process, and a barrier of those threads that a failing shard breaks, so the
// others stop with an error instead of waiting for it (core/tensor_parallel.hpp).
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"

namespace epona::cuda {

class DeviceShardThreads {
 public:
  // `who` names the group in errors; `share_devices` lets a GPU hold several shards (tests).
  DeviceShardThreads(std::vector<int> devices, const std::string& who, int max_shards, bool share_devices = false)
      : devices_(checked(std::move(devices), who, max_shards, share_devices)),
        barrier_(static_cast<std::int64_t>(devices_.size())) {}

  std::int64_t size() const { return static_cast<std::int64_t>(devices_.size()); }
  int device(std::int64_t rank) const { return devices_.at(static_cast<std::size_t>(rank)); }
  const std::vector<int>& devices() const { return devices_; }

  // Runs f(rank) in one thread per shard and waits for all (run_shard_threads), thread r's
  // current device device(r): the Contexts (and world models) it makes live there.
  template <class F>
  void run(F&& f) {
    run_shard_threads(size(), barrier_, [&](std::int64_t r) {
      EPONA_CUDA_CHECK(cudaSetDevice(device(r)));
      f(r);
    });
  }

  // Every rank arrives before any goes on (a failed rank breaks it: the others throw).
  void fence() { barrier_.arrive_and_wait(); }

  // True while ctx's stream records a graph: the group's fence is then left on the context, and
  // the graph calls it before and after every launch (Context::note_captured_collective).
  bool fence_recorded_graph(Context& ctx) {
    cudaStreamCaptureStatus capture = cudaStreamCaptureStatusNone;
    EPONA_CUDA_CHECK(cudaStreamIsCapturing(ctx.stream(), &capture));
    if (capture != cudaStreamCaptureStatusActive) return false;
    ctx.note_captured_collective([this] { fence(); });
    return true;
  }

 private:
  static std::vector<int> checked(std::vector<int> devices, const std::string& who, int max_shards,
                                  bool share_devices) {
    int present = 0;
    EPONA_CUDA_CHECK(cudaGetDeviceCount(&present));
    EPONA_CHECK(!devices.empty() && devices.size() <= static_cast<std::size_t>(max_shards), who, ": ", devices.size(),
                " devices (1 to ", max_shards, ")");
    for (std::size_t i = 0; i < devices.size(); ++i) {
      EPONA_CHECK(devices[i] >= 0 && devices[i] < std::min(present, kMaxDevices), who, ": device ", devices[i],
                  " does not exist (", present, " present)");
      for (std::size_t j = 0; j < i; ++j)
        EPONA_CHECK(share_devices || devices[i] != devices[j], who, ": device ", devices[i],
                    " twice (a group needs one GPU per shard)");
    }
    return devices;
  }

  std::vector<int> devices_;
  BreakableBarrier barrier_;
};

}  // namespace epona::cuda
