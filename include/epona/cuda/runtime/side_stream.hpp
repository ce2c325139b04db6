// epona/cuda/runtime/side_stream.hpp — a second stream for work that may overlap the main stream's
// (the condition and target streams of a DiT double block, the MLP and attention projections
// of a single block): a context of its own (stream, cuBLASLt handle, workspace) created once,
// and fork/join through events, which a CUDA graph capture records as parallel branches.
#pragma once

#include <cuda_runtime.h>

#include <memory>
#include <utility>

#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"

namespace epona::cuda {

class SideStream {
 public:
  SideStream() = default;
  // A copy starts empty (it creates its own context when first used).
  SideStream(const SideStream&) {}
  SideStream& operator=(const SideStream& o) {
    if (this != &o) release();
    return *this;
  }
  SideStream(SideStream&& o) noexcept
      : side_(std::move(o.side_)), fork_(std::exchange(o.fork_, nullptr)), join_(std::exchange(o.join_, nullptr)) {}
  SideStream& operator=(SideStream&& o) noexcept {
    if (this != &o) {
      release();
      side_ = std::move(o.side_);
      fork_ = std::exchange(o.fork_, nullptr);
      join_ = std::exchange(o.join_, nullptr);
    }
    return *this;
  }
  ~SideStream() { release(); }

  // The side context (created on the main context's device on first use: call once outside
  // any graph capture).
  Context& side(Context& main) {
    if (!side_) {
      side_ = std::make_unique<Context>(main.info().device);
      EPONA_CUDA_CHECK(cudaEventCreateWithFlags(&fork_, cudaEventDisableTiming));
      EPONA_CUDA_CHECK(cudaEventCreateWithFlags(&join_, cudaEventDisableTiming));
    }
    side_->policy() = main.policy();  // the side stream's kernels take the main context's choices
    return *side_;
  }
  // The side stream waits for everything queued on main so far.
  void fork(Context& main) {
    side(main);
    EPONA_CUDA_CHECK(cudaEventRecord(fork_, main.stream()));
    EPONA_CUDA_CHECK(cudaStreamWaitEvent(side_->stream(), fork_, 0));
  }
  // Main waits for everything queued on the side stream so far.
  void join(Context& main) {
    EPONA_CUDA_CHECK(cudaEventRecord(join_, side(main).stream()));
    EPONA_CUDA_CHECK(cudaStreamWaitEvent(main.stream(), join_, 0));
  }

 private:
  void release() {
    if (fork_) cudaEventDestroy(fork_);
    if (join_) cudaEventDestroy(join_);
    fork_ = join_ = nullptr;
    side_.reset();
  }
  std::unique_ptr<Context> side_;
  cudaEvent_t fork_ = nullptr, join_ = nullptr;
};

}  // namespace epona::cuda
