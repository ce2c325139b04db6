// epona/cpu/thread_shard_sum.hpp — a tensor-parallel group of threads of one process on the CPU:
// shard r runs in thread r with its own Context, and ShardSum adds the shards' buffers through
// shared memory. It makes the sharded model testable without GPUs (tests/model/dit_shards.cpp).
// The sum is the same on every shard bit for bit: each element is added in rank order, chunk c of
// the buffer by shard c, and every shard copies the result.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cpu/context.hpp"

namespace epona::cpu {

class ThreadShardGroup {
 public:
  explicit ThreadShardGroup(std::int64_t size)
      : size_(size), barrier_(size), buffers_(static_cast<std::size_t>(size)), counts_(buffers_.size()) {}

  std::int64_t size() const { return size_; }

  using Sum = GroupShardSum<ThreadShardGroup, Context, float>;
  Sum shard(std::int64_t rank) { return Sum(*this, rank); }

  // Runs f(rank) in one thread per shard and waits for all (run_shard_threads).
  template <class F>
  void run(F&& f) {
    run_shard_threads(size_, barrier_, f);
  }

  // Shard `rank`'s part of a sum (its ShardSum's call).
  void sum(Context&, std::int64_t rank, float* data, std::int64_t count) {
    const auto r = static_cast<std::size_t>(rank);
    buffers_[r] = data;
    counts_[r] = count;
    barrier_.arrive_and_wait([&] {
      mismatch_ = !std::all_of(counts_.begin(), counts_.end(), [&](std::int64_t c) { return c == counts_[0]; });
      if (!mismatch_) result_.resize(static_cast<std::size_t>(count));
    });
    EPONA_CHECK(!mismatch_, "ThreadShardGroup: the shards summed buffers of different sizes");
    const std::int64_t chunk = (count + size_ - 1) / size_, begin = std::min(count, rank * chunk),
                       end = std::min(count, begin + chunk);
    for (std::int64_t i = begin; i < end; ++i) {
      float s = buffers_[0][i];
      for (std::size_t j = 1; j < buffers_.size(); ++j) s += buffers_[j][i];
      result_[static_cast<std::size_t>(i)] = s;
    }
    barrier_.arrive_and_wait();
    // The next sum's first barrier (which resizes result_) waits for every shard's copy.
    std::copy_n(result_.data(), count, data);
  }

 private:
  std::int64_t size_;
  BreakableBarrier barrier_;
  std::vector<float*> buffers_;
  std::vector<std::int64_t> counts_;
  std::vector<float> result_;
  bool mismatch_ = false;
};

}  // namespace epona::cpu
