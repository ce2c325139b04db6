// epona/cuda/runtime/nccl_shard_sum.hpp — a tensor-parallel group over the GPUs of one host through
// NCCL: one process drives them (ncclCommInitAll), shard r runs in host thread r with a
// cuda::Context on devices[r], and ShardSum is ncclAllReduce on that context's stream, so a
// recorded sampler graph holds it. Keep NVLink multicast off (NCCL_NVLS_ENABLE=0) on the lent
// machines (docs/parallel.md). The one header that includes <nccl.h>: link NCCL (CMake target
// epona_nccl) where it is used.
#pragma once

#include <nccl.h>

#include <cstdint>
#include <type_traits>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cuda/runtime/context.hpp"

#define EPONA_NCCL_CHECK(expr)                                                                    \
  do {                                                                                            \
    const ncclResult_t epona_nccl_status_ = (expr);                                               \
    if (epona_nccl_status_ != ncclSuccess)                                                        \
      ::epona::fail("NCCL: ", #expr, " failed: ", ncclGetErrorString(epona_nccl_status_));        \
  } while (0)

namespace epona::cuda {

template <class A>
class NcclShardGroup {
  static_assert(std::is_same_v<A, float> || std::is_same_v<A, bf16>, "NcclShardGroup: float or bf16 activations");

 public:
  // Shard r on GPU devices[r]; every device once (NCCL refuses two ranks on one GPU).
  explicit NcclShardGroup(std::vector<int> devices) : devices_(std::move(devices)), barrier_(devices_.size()) {
    int present = 0;
    EPONA_CUDA_CHECK(cudaGetDeviceCount(&present));
    EPONA_CHECK(!devices_.empty(), "NcclShardGroup: no devices");
    for (std::size_t i = 0; i < devices_.size(); ++i) {
      EPONA_CHECK(devices_[i] >= 0 && devices_[i] < present, "NcclShardGroup: device ", devices_[i], " does not exist (",
                  present, " present)");
      for (std::size_t j = 0; j < i; ++j)
        EPONA_CHECK(devices_[i] != devices_[j], "NcclShardGroup: device ", devices_[i],
                    " twice (a group needs one GPU per shard)");
    }
    comms_.resize(devices_.size());
    EPONA_NCCL_CHECK(ncclCommInitAll(comms_.data(), static_cast<int>(devices_.size()), devices_.data()));
  }
  ~NcclShardGroup() {
    for (auto c : comms_)
      if (c) (void)ncclCommDestroy(c);
  }
  NcclShardGroup(const NcclShardGroup&) = delete;
  NcclShardGroup& operator=(const NcclShardGroup&) = delete;

  std::int64_t size() const { return static_cast<std::int64_t>(devices_.size()); }
  int device(std::int64_t rank) const { return devices_.at(static_cast<std::size_t>(rank)); }

  using Sum = GroupShardSum<NcclShardGroup, Context, A>;
  Sum shard(std::int64_t rank) { return Sum(*this, rank); }

  // Runs f(rank) in one thread per shard and waits for all (run_shard_threads), thread r's
  // current device device(r): the Contexts (and world models) it makes live there.
  template <class F>
  void run(F&& f) {
    run_shard_threads(size(), barrier_, [&](std::int64_t r) {
      EPONA_CUDA_CHECK(cudaSetDevice(device(r)));
      f(r);
    });
  }

  // Shard `rank`'s all-reduce on its context's stream (its ShardSum's call).
  void sum(Context& ctx, std::int64_t rank, A* data, std::int64_t count) {
    constexpr ncclDataType_t type = std::is_same_v<A, float> ? ncclFloat32 : ncclBfloat16;
    EPONA_NCCL_CHECK(ncclAllReduce(data, data, static_cast<std::size_t>(count), type, ncclSum,
                                   comms_[static_cast<std::size_t>(rank)], ctx.stream()));
  }

 private:
  std::vector<int> devices_;
  std::vector<ncclComm_t> comms_;
  BreakableBarrier barrier_;
};

}  // namespace epona::cuda
