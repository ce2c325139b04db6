// epona/cuda/runtime/nccl_shard_sum.hpp — a tensor-parallel group over the GPUs of one host through
// NCCL: one process drives them (ncclCommInitAll), shard r runs in host thread r with a
// cuda::Context on devices[r], and ShardSum is ncclAllReduce on that context's stream, so a
// recorded sampler graph holds it. Every rank launches a collective (or a graph holding one)
// between two barriers of the group, so no rank's CUDA call can wait on a GPU whose collective
// waits for that rank, and a failed rank stops the others before they launch (context.hpp;
// docs/parallel.md, "the group's fences"). Keep NVLink multicast off (NCCL_NVLS_ENABLE=0) on the
// lent machines. The one header that includes <nccl.h>: link NCCL (CMake target epona_nccl)
// where it is used.
#pragma once

#include <nccl.h>

#include <cstdint>
#include <type_traits>
#include <utility>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device_shard_threads.hpp"
#include "epona/cuda/runtime/memory.hpp"

#define EPONA_NCCL_CHECK(expr)                                                                    \
  do {                                                                                            \
    const ncclResult_t epona_nccl_status_ = (expr);                                               \
    if (epona_nccl_status_ != ncclSuccess)                                                        \
      ::epona::fail("NCCL: ", #expr, " failed: ", ncclGetErrorString(epona_nccl_status_));        \
  } while (0)

namespace epona::cuda {

template <class A>
class NcclShardGroup : public DeviceShardThreads {
  static_assert(std::is_same_v<A, float> || std::is_same_v<A, bf16>, "NcclShardGroup: float or bf16 activations");

 public:
  // Shard r on GPU devices[r]; every device once (NCCL refuses two ranks on one GPU).
  explicit NcclShardGroup(std::vector<int> devices)
      : DeviceShardThreads(std::move(devices), "NcclShardGroup", kMaxDevices) {
    comms_.resize(static_cast<std::size_t>(size()));
    EPONA_NCCL_CHECK(ncclCommInitAll(comms_.data(), static_cast<int>(size()), DeviceShardThreads::devices().data()));
    try {
      connect();
    } catch (...) {
      destroy();
      throw;
    }
  }
  ~NcclShardGroup() { destroy(); }
  NcclShardGroup(const NcclShardGroup&) = delete;
  NcclShardGroup& operator=(const NcclShardGroup&) = delete;

  using Sum = GroupShardSum<NcclShardGroup, Context, A>;
  Sum shard(std::int64_t rank) { return Sum(*this, rank); }

  // Shard `rank`'s all-reduce on its context's stream (its ShardSum's call): launched between two
  // barriers, or, while the stream records a graph, left to the graph's launches to fence.
  void sum(Context& ctx, std::int64_t rank, A* data, std::int64_t count) {
    if (size() == 1 || fence_recorded_graph(ctx)) return all_reduce(ctx.stream(), rank, data, count);
    fence();
    all_reduce(ctx.stream(), rank, data, count);
    fence();
  }

 private:
  void all_reduce(cudaStream_t stream, std::int64_t rank, A* data, std::int64_t count) {
    constexpr ncclDataType_t type = std::is_same_v<A, float> ? ncclFloat32 : ncclBfloat16;
    EPONA_NCCL_CHECK(ncclAllReduce(data, data, static_cast<std::size_t>(count), type, ncclSum,
                                   comms_[static_cast<std::size_t>(rank)], stream));
  }

  // One all-reduce of one element on every rank: NCCL connects the ranks at their first
  // collective, so a group that cannot talk fails here, at its construction, and the models'
  // first sums (often inside a graph's recording) find the connections made.
  void connect() {
    if (size() == 1) return;
    run([&](std::int64_t r) {
      Context ctx(device(r), 0);
      const auto one = BackendMemory<Cuda>::allocate(sizeof(A));
      EPONA_CUDA_CHECK(cudaMemsetAsync(one.get(), 0, sizeof(A), ctx.stream()));
      fence();
      all_reduce(ctx.stream(), r, static_cast<A*>(one.get()), 1);
      fence();
      ctx.synchronize();
    });
  }

  void destroy() {
    for (auto& c : comms_)
      if (c) (void)ncclCommDestroy(std::exchange(c, nullptr));
  }

  std::vector<ncclComm_t> comms_;
};

}  // namespace epona::cuda
