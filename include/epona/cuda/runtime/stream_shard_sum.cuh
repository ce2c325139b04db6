// epona/cuda/runtime/stream_shard_sum.cuh — a tensor-parallel group whose shards share one GPU:
// shard r runs in host thread r with a cuda::Context of its own (its own stream) on `device`,
// and ShardSum adds the shards' buffers there, ordered by events between the streams. It runs
// the sharded model's kernels where only one GPU is at hand (NCCL refuses two ranks on one
// device): for tests, not for speed (tests/cuda/dit_shards.cu; the real group is NCCL's).
// The streams wait on each other's events, which a recorded graph cannot hold across threads:
// the shards' contexts run with graphs off (policy().graphs = false), and the sum says so if not.
// The sum is the same on every shard bit for bit: chunk c of the buffer is added by shard c, in
// rank order in float32, rounded once to A, and every shard copies the result.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace detail {
inline constexpr int kMaxStreamShards = 8;

// out[c] = Σ_j parts[j][c] in rank order (float32), rounded to A.
template <class A>
struct ShardSumEach {
  const A* parts[kMaxStreamShards];
  int count;
  A* out;
  __device__ void pack(std::int64_t, std::int64_t c) const {
    float acc[kPack], v[kPack];
    load8(parts[0] + c, acc);
    for (int j = 1; j < count; ++j) {
      load8(parts[j] + c, v);
#pragma unroll
      for (int k = 0; k < kPack; ++k) acc[k] += v[k];
    }
    store8(out + c, acc);
  }
  __device__ void one(std::int64_t, std::int64_t c) const {
    float acc = to_f32(parts[0][c]);
    for (int j = 1; j < count; ++j) acc += to_f32(parts[j][c]);
    out[c] = from_f32<A>(acc);
  }
};
}  // namespace detail

template <class A>
class StreamShardGroup {
 public:
  StreamShardGroup(std::int64_t size, int device = 0)
      : size_(size), device_(device), barrier_(size), buffers_(static_cast<std::size_t>(size)),
        counts_(buffers_.size()) {
    EPONA_CHECK(size >= 1 && size <= detail::kMaxStreamShards, "StreamShardGroup: ", size, " shards (1 to ",
                detail::kMaxStreamShards, ")");
    EPONA_CUDA_CHECK(cudaSetDevice(device));
    for (auto* events : {&ready_, &summed_, &copied_})
      for (std::int64_t r = 0; r < size; ++r) {
        cudaEvent_t e = nullptr;
        EPONA_CUDA_CHECK(cudaEventCreateWithFlags(&e, cudaEventDisableTiming));
        events->push_back(e);
      }
  }
  ~StreamShardGroup() {
    (void)cudaSetDevice(device_);
    (void)cudaDeviceSynchronize();
    for (auto* events : {&ready_, &summed_, &copied_})
      for (auto e : *events) (void)cudaEventDestroy(e);
    if (result_) (void)cudaFree(result_);
  }
  StreamShardGroup(const StreamShardGroup&) = delete;
  StreamShardGroup& operator=(const StreamShardGroup&) = delete;

  std::int64_t size() const { return size_; }
  int device() const { return device_; }

  using Sum = GroupShardSum<StreamShardGroup, Context, A>;
  Sum shard(std::int64_t rank) { return Sum(*this, rank); }

  // Runs f(rank) in one thread per shard and waits for all (run_shard_threads), each thread's
  // current device device(): the Contexts (and world models) it makes live there.
  template <class F>
  void run(F&& f) {
    run_shard_threads(size_, barrier_, [&](std::int64_t r) {
      EPONA_CUDA_CHECK(cudaSetDevice(device_));
      f(r);
    });
  }

  // Shard `rank`'s part of a sum (its ShardSum's call).
  void sum(Context& ctx, std::int64_t rank, A* data, std::int64_t count) {
    EPONA_CHECK(!ctx.policy().graphs, "StreamShardGroup: its shards' contexts must run with graphs off "
                                      "(policy().graphs = false): a graph cannot wait on another thread's stream");
    const auto r = static_cast<std::size_t>(rank);
    buffers_[r] = data;
    counts_[r] = count;
    EPONA_CUDA_CHECK(cudaEventRecord(ready_[r], ctx.stream()));
    barrier_.arrive_and_wait([&] { prepare(count); });
    EPONA_CHECK(!mismatch_, "StreamShardGroup: the shards summed buffers of different sizes");
    EPONA_CHECK(prepare_error_ == cudaSuccess, "StreamShardGroup: ", cudaGetErrorString(prepare_error_));
    // Every part is written, and every shard has copied the previous result out of result_.
    for (std::size_t j = 0; j < buffers_.size(); ++j) {
      EPONA_CUDA_CHECK(cudaStreamWaitEvent(ctx.stream(), ready_[j], 0));
      EPONA_CUDA_CHECK(cudaStreamWaitEvent(ctx.stream(), copied_[j], 0));
    }
    const std::int64_t chunk = (count + size_ - 1) / size_, begin = std::min(count, rank * chunk),
                       end = std::min(count, begin + chunk);
    detail::ShardSumEach<A> each{};
    each.count = static_cast<int>(size_);
    each.out = result_ + begin;
    bool aligned = (end - begin) % detail::kPack == 0 && begin % detail::kPack == 0;
    for (std::size_t j = 0; j < buffers_.size(); ++j) {
      each.parts[j] = buffers_[j] + begin;
      aligned = aligned && reinterpret_cast<std::uintptr_t>(buffers_[j]) % 16 == 0;
    }
    detail::for_each(ctx, 1, end - begin, aligned, each);
    EPONA_CUDA_CHECK(cudaEventRecord(summed_[r], ctx.stream()));
    barrier_.arrive_and_wait();
    for (std::size_t j = 0; j < buffers_.size(); ++j) EPONA_CUDA_CHECK(cudaStreamWaitEvent(ctx.stream(), summed_[j], 0));
    EPONA_CUDA_CHECK(cudaMemcpyAsync(data, result_, static_cast<std::size_t>(count) * sizeof(A),
                                     cudaMemcpyDeviceToDevice, ctx.stream()));
    EPONA_CUDA_CHECK(cudaEventRecord(copied_[r], ctx.stream()));
  }

 private:
  // In the last thread to arrive, before any goes on: the sizes agree, and result_ holds them
  // (a larger one replaces it once every stream is idle).
  void prepare(std::int64_t count) {
    mismatch_ = !std::all_of(counts_.begin(), counts_.end(), [&](std::int64_t c) { return c == counts_[0]; });
    if (mismatch_ || count <= capacity_) return;
    prepare_error_ = cudaSetDevice(device_);
    if (prepare_error_ == cudaSuccess) prepare_error_ = cudaDeviceSynchronize();
    if (result_) (void)cudaFree(result_);
    result_ = nullptr;
    capacity_ = 0;
    if (prepare_error_ == cudaSuccess) prepare_error_ = cudaMalloc(&result_, static_cast<std::size_t>(count) * sizeof(A));
    if (prepare_error_ == cudaSuccess) capacity_ = count;
  }

  std::int64_t size_;
  int device_;
  BreakableBarrier barrier_;
  std::vector<A*> buffers_;
  std::vector<std::int64_t> counts_;
  std::vector<cudaEvent_t> ready_, summed_, copied_;
  A* result_ = nullptr;
  std::int64_t capacity_ = 0;
  bool mismatch_ = false;
  cudaError_t prepare_error_ = cudaSuccess;
};

}  // namespace epona::cuda
