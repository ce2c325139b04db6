// epona/core/tensor_parallel.hpp — tensor parallelism's two backend-neutral pieces (docs/parallel.md):
// which shard of a group a model part is, and the one collective its blocks need. A DiT shard
// holds heads/size of the attention heads and mlp_hidden/size of the MLP columns; its products
// into the residual width (attention out, MLP out) give partial sums, which ShardSum adds up over
// the group before the residual add (Megatron-style: one all-reduce per sublayer). The
// implementations live with their backends: threads of one process on the CPU
// (cpu/thread_shard_sum.hpp), NCCL between GPUs and streams of one GPU on CUDA.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <exception>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "epona/core/error.hpp"

namespace epona {

// Shard `rank` of a tensor-parallel group of `size`.
struct TensorShard {
  std::int64_t rank = 0, size = 1;

  bool sharded() const { return size > 1; }
  // Refuses a rank outside the group; `what` names the caller in the message.
  void check(const std::string& what) const {
    EPONA_CHECK(size >= 1 && rank >= 0 && rank < size, what, ": shard ", rank, " of ", size,
                " (the rank must lie in [0, size), the size be at least 1)");
  }
  // This shard's part [begin, end) of `n` (which the size divides).
  std::int64_t part_begin(std::int64_t n) const { return rank * (n / size); }
  std::int64_t part_end(std::int64_t n) const { return (rank + 1) * (n / size); }
};

// Sums `count` elements of A at `data` over the group's shards, in place, on every shard alike
// (an all-reduce). Every shard calls it with the same count, in the same order.
template <class Context, class A>
class ShardSum {
 public:
  virtual ~ShardSum() = default;
  virtual std::int64_t size() const = 0;
  virtual void sum(Context& ctx, A* data, std::int64_t count) const = 0;
};

// One shard's ShardSum of a group that sums for every rank: group.sum(ctx, rank, data, count)
// (cpu::ThreadShardGroup, cuda::StreamShardGroup, cuda::NcclShardGroup).
template <class Group, class Context, class A>
class GroupShardSum final : public ShardSum<Context, A> {
 public:
  GroupShardSum(Group& group, std::int64_t rank) : group_(&group), rank_(rank) {
    TensorShard{rank, group.size()}.check("tensor-parallel group");
  }
  std::int64_t size() const override { return group_->size(); }
  void sum(Context& ctx, A* data, std::int64_t count) const override { group_->sum(ctx, rank_, data, count); }

 private:
  Group* group_;
  std::int64_t rank_;
};

// A barrier of a fixed number of threads that a failing thread can break: the others then
// throw instead of waiting for ever (a shard whose work threw never arrives).
class BreakableBarrier {
 public:
  explicit BreakableBarrier(std::int64_t count) : count_(count) {
    EPONA_CHECK(count >= 1, "barrier of ", count, " threads");
  }
  // Waits until every thread has arrived; `on_last` runs once, in the last thread to arrive,
  // before any thread goes on.
  template <class F>
  void arrive_and_wait(F&& on_last) {
    std::unique_lock lock(mutex_);
    EPONA_CHECK(!broken_, "tensor-parallel group: another shard failed");
    const std::uint64_t generation = generation_;
    if (++arrived_ == count_) {
      on_last();
      arrived_ = 0;
      ++generation_;
      changed_.notify_all();
      return;
    }
    changed_.wait(lock, [&] { return generation_ != generation || broken_; });
    EPONA_CHECK(!broken_, "tensor-parallel group: another shard failed");
  }
  void arrive_and_wait() {
    arrive_and_wait([] {});
  }
  // Wakes every waiting thread with an error, now and at every later arrival.
  void break_barrier() {
    std::lock_guard lock(mutex_);
    broken_ = true;
    changed_.notify_all();
  }

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  std::int64_t count_, arrived_ = 0;
  std::uint64_t generation_ = 0;
  bool broken_ = false;
};

// Runs f(rank) for every rank of a group of `size` in a thread of its own and waits for all
// (a group of one process: cpu::ThreadShardGroup, cuda::StreamShardGroup). A rank that throws
// breaks the group's barrier, so the others stop with an error instead of waiting for it; the
// first error in time (the cause) is rethrown. A group that failed stays failed.
template <class F>
void run_shard_threads(std::int64_t size, BreakableBarrier& barrier, F&& f) {
  std::exception_ptr first;
  std::mutex first_mutex;
  std::vector<std::thread> threads;
  for (std::int64_t r = 0; r < size; ++r)
    threads.emplace_back([&, r] {
      try {
        f(r);
      } catch (...) {
        {
          std::lock_guard lock(first_mutex);
          if (!first) first = std::current_exception();
        }
        barrier.break_barrier();
      }
    });
  for (auto& t : threads) t.join();
  if (first) std::rethrow_exception(first);
}

}  // namespace epona
