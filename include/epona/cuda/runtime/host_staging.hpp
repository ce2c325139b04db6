// epona/cuda/runtime/host_staging.hpp — host -> device uploads that do not wait for the stream. A copy
// from pageable host memory first waits for everything queued on the stream, so an upload at
// the start of a model call (the MST's pose features, a sampler's timestep embeddings) let the
// GPU drain and then idle while the host launched the next kernels. Here the bytes go through a
// ring of pinned host memory instead: the call copies them there and queues the transfer, and
// a span of the ring is written again only after the transfer that last read it has run (an
// event per upload). The ring is allocated on first use.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstring>
#include <deque>
#include <vector>

#include "epona/cuda/runtime/check.hpp"

namespace epona::cuda {

class HostStaging {
 public:
  static constexpr std::size_t default_capacity = std::size_t{4} << 20;

  // Every upload goes to `stream` (so the transfers run in the order they were queued).
  explicit HostStaging(cudaStream_t stream, std::size_t capacity = default_capacity)
      : stream_(stream), capacity_(capacity) {}
  HostStaging(const HostStaging&) = delete;
  HostStaging& operator=(const HostStaging&) = delete;
  ~HostStaging() {
    for (const auto& u : pending_) (void)cudaEventSynchronize(u.done);  // no transfer may outlive the ring
    for (const auto& u : pending_) (void)cudaEventDestroy(u.done);
    for (auto e : free_events_) (void)cudaEventDestroy(e);
    if (ring_) (void)cudaFreeHost(ring_);
  }

  // Queues dst <- src (`bytes` bytes) on the stream and returns without waiting for the stream;
  // src may be reused at once. False, with nothing done, where the ring cannot take it: more
  // bytes than it holds, a stream being captured into a graph (a recorded copy would read the
  // ring when replayed, long after it was refilled), or no pinned memory to be had.
  bool upload(void* dst, const void* src, std::size_t bytes) {
    if (bytes == 0) return true;
    if (bytes > capacity_ || detail::capturing(stream_) || !allocate()) return false;
    const std::size_t offset = reserve(bytes);
    std::memcpy(ring_ + offset, src, bytes);
    EPONA_CUDA_CHECK(cudaMemcpyAsync(dst, ring_ + offset, bytes, cudaMemcpyHostToDevice, stream_));
    const cudaEvent_t done = take_event();
    EPONA_CUDA_CHECK(cudaEventRecord(done, stream_));
    pending_.push_back({offset, offset + bytes, done});
    return true;
  }

 private:
  struct Pending {
    std::size_t begin, end;  // the span of the ring its transfer reads
    cudaEvent_t done;
  };

  bool allocate() {
    if (ring_) return true;
    void* p = nullptr;
    if (cudaMallocHost(&p, capacity_) != cudaSuccess) {
      (void)cudaGetLastError();  // the caller falls back to a pageable copy
      return false;
    }
    ring_ = static_cast<unsigned char*>(p);
    return true;
  }

  // The next span of `bytes` (from head_, or from the start when it does not fit before the
  // end), once every earlier transfer reading any of it has run. The transfers run in queue
  // order (one stream), so waiting for the newest of them retires every older one too.
  std::size_t reserve(std::size_t bytes) {
    const std::size_t offset = head_ + bytes <= capacity_ ? head_ : 0, end = offset + bytes;
    std::size_t newest = pending_.size();
    for (std::size_t i = 0; i < pending_.size(); ++i)
      if (pending_[i].begin < end && offset < pending_[i].end) newest = i;
    if (newest < pending_.size())
      for (std::size_t i = 0; i <= newest; ++i) retire_front();
    head_ = end;
    return offset;
  }
  void retire_front() {
    const Pending u = pending_.front();
    pending_.pop_front();
    EPONA_CUDA_CHECK(cudaEventSynchronize(u.done));
    free_events_.push_back(u.done);
  }
  cudaEvent_t take_event() {
    // Transfers that have run free their events without waiting (keeps the queue short).
    while (!pending_.empty() && cudaEventQuery(pending_.front().done) == cudaSuccess) retire_front();
    (void)cudaGetLastError();  // cudaEventQuery's cudaErrorNotReady is not an error here
    if (!free_events_.empty()) {
      const cudaEvent_t e = free_events_.back();
      free_events_.pop_back();
      return e;
    }
    cudaEvent_t e = nullptr;
    EPONA_CUDA_CHECK(cudaEventCreateWithFlags(&e, cudaEventDisableTiming));
    return e;
  }

  cudaStream_t stream_;
  std::size_t capacity_;
  unsigned char* ring_ = nullptr;
  std::size_t head_ = 0;
  std::deque<Pending> pending_;
  std::vector<cudaEvent_t> free_events_;
};

}  // namespace epona::cuda
