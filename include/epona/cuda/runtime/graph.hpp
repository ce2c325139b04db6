// epona/cuda/runtime/graph.hpp — replaying a recorded sequence of kernels as a CUDA graph. A sampler's
// loop (100 steps of a few hundred small launches) is captured once from the context's stream
// and then relaunched as one graph while it is fed the same buffers: the key names those
// buffers and sizes, and a different key records the loop again. ctx.policy().graphs off
// (EPONA_CUDA_GRAPHS=0) turns capture off (the work then runs directly on the stream, e.g. for debugging). The recorded
// graph's nodes are counted (kernels per sampling step, for the benchmark).
#pragma once

#include <cuda_runtime.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <utility>
#include <vector>

#include "epona/core/env.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"

namespace epona::cuda {


class GraphCache {
 public:
  GraphCache() = default;
  // A copy starts empty: a graph is bound to the buffers of the object that recorded it.
  GraphCache(const GraphCache&) {}
  GraphCache& operator=(const GraphCache& o) {
    if (this != &o) reset();
    return *this;
  }
  GraphCache(GraphCache&& o) noexcept
      : exec_(std::exchange(o.exec_, nullptr)), key_(std::move(o.key_)), captures_(o.captures_),
        capture_ms_(o.capture_ms_), counts_(o.counts_), fence_(std::move(o.fence_)) {}
  GraphCache& operator=(GraphCache&& o) noexcept {
    if (this != &o) {
      reset();
      exec_ = std::exchange(o.exec_, nullptr);
      key_ = std::move(o.key_);
      captures_ = o.captures_;
      capture_ms_ = o.capture_ms_;
      counts_ = o.counts_;
      fence_ = std::move(o.fence_);
    }
    return *this;
  }
  ~GraphCache() { reset(); }

  // Runs `work` (which only enqueues asynchronous work on ctx's stream: no host
  // synchronisation, no allocation) through the graph recorded under `key`, recording it first
  // when the key is new.
  template <class Work>
  void run(Context& ctx, const std::vector<std::uint64_t>& key, Work&& work) {
    if (!ctx.policy().graphs) {
      work();
      return;
    }
    if (!exec_ || key != key_) record(ctx, key, work);
    if (fence_) fence_();  // a graph holding collectives: every rank launches between two fences
    EPONA_CUDA_CHECK(cudaGraphLaunch(exec_, ctx.stream()));
    if (fence_) fence_();
  }

  // What the last recorded graph holds: all nodes, kernels (cuBLASLt's included), memory
  // copies and sets (the rest are event/empty nodes of the fork/join pattern).
  struct NodeCounts {
    std::size_t nodes = 0, kernels = 0, copies = 0;
  };
  int captures() const { return captures_; }          // how often a graph was recorded
  const NodeCounts& node_counts() const { return counts_; }
  double last_capture_ms() const { return capture_ms_; }  // host time of the last capture + instantiation
  void reset() {
    if (exec_) cudaGraphExecDestroy(exec_);
    exec_ = nullptr;
    key_.clear();
    fence_ = {};
  }
  bool holds_collectives() const { return static_cast<bool>(fence_); }

 private:
  template <class Work>
  void record(Context& ctx, const std::vector<std::uint64_t>& key, Work& work) {
    reset();
    const auto start = std::chrono::steady_clock::now();
    cudaGraph_t graph = nullptr;
    (void)ctx.take_captured_collective();
    // Relaxed: first calls inside the capture may build cuBLASLt plans or set kernel attributes.
    EPONA_CUDA_CHECK(cudaStreamBeginCapture(ctx.stream(), cudaStreamCaptureModeRelaxed));
    try {
      work();
    } catch (...) {
      (void)cudaStreamEndCapture(ctx.stream(), &graph);  // leave the stream usable
      if (graph) cudaGraphDestroy(graph);
      (void)cudaGetLastError();
      throw;
    }
    EPONA_CUDA_CHECK(cudaStreamEndCapture(ctx.stream(), &graph));
    std::function<void()> fence = ctx.take_captured_collective();
    count_nodes(graph);
    const cudaError_t status = cudaGraphInstantiate(&exec_, graph, 0);
    cudaGraphDestroy(graph);
    if (status != cudaSuccess) exec_ = nullptr;
    EPONA_CUDA_CHECK(status);
    // Uploaded here, so the first launch between the fences does no more than later ones.
    EPONA_CUDA_CHECK(cudaGraphUpload(exec_, ctx.stream()));
    fence_ = std::move(fence);
    key_ = key;
    ++captures_;
    capture_ms_ = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  }

  void count_nodes(cudaGraph_t graph) {
    std::size_t n = 0;
    EPONA_CUDA_CHECK(cudaGraphGetNodes(graph, nullptr, &n));
    std::vector<cudaGraphNode_t> nodes(n);
    if (n) EPONA_CUDA_CHECK(cudaGraphGetNodes(graph, nodes.data(), &n));
    counts_ = {n, 0, 0};
    for (auto node : nodes) {
      cudaGraphNodeType type{};
      EPONA_CUDA_CHECK(cudaGraphNodeGetType(node, &type));
      counts_.kernels += type == cudaGraphNodeTypeKernel;
      counts_.copies += type == cudaGraphNodeTypeMemcpy || type == cudaGraphNodeTypeMemset;
    }
  }

  cudaGraphExec_t exec_ = nullptr;
  std::vector<std::uint64_t> key_;
  int captures_ = 0;
  double capture_ms_ = 0;
  NodeCounts counts_;
  std::function<void()> fence_;  // set when the recorded graph holds a collective between GPUs
};

}  // namespace epona::cuda
