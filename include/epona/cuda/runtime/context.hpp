// epona/cuda/runtime/context.hpp — the CUDA backend's execution context: one device, one stream that
// every kernel and copy of the context is ordered on, the cuBLASLt handle with its workspace
// and cached matmul plans, the device's properties and the kernel policy its kernels read
// (kernel_policy.hpp). has_gpu() lets tests skip cleanly.
#pragma once

#include <cublasLt.h>
#include <cuda_runtime.h>

#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <utility>

#include "epona/core/error.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/host_staging.hpp"
#include "epona/cuda/runtime/kernel_policy.hpp"

namespace epona::cuda {

// The most devices that per-device tables hold (the scratch pools, the kernels' shared memory
// attribute).
inline constexpr int kMaxDevices = 64;

// True when the CUDA runtime sees at least one device (false without a driver, too).
inline bool has_gpu() {
  static const bool present = [] {
    int count = 0;
    const cudaError_t status = cudaGetDeviceCount(&count);
    if (status != cudaSuccess) {
      (void)cudaGetLastError();  // clear the error so later calls start clean
      return false;
    }
    return count > 0;
  }();
  return present;
}

struct DeviceInfo {
  int device = 0;
  std::string name;
  int major = 0, minor = 0;          // compute capability
  int multiprocessors = 0;
  std::size_t global_bytes = 0;
  std::size_t l2_bytes = 0;
  std::size_t smem_per_block_optin = 0;  // the most dynamic shared memory one block may ask for

  static DeviceInfo query(int device) {
    cudaDeviceProp p{};
    EPONA_CUDA_CHECK(cudaGetDeviceProperties(&p, device));
    DeviceInfo d;
    d.device = device;
    d.name = p.name;
    d.major = p.major;
    d.minor = p.minor;
    d.multiprocessors = p.multiProcessorCount;
    d.global_bytes = p.totalGlobalMem;
    d.l2_bytes = static_cast<std::size_t>(p.l2CacheSize);
    d.smem_per_block_optin = p.sharedMemPerBlockOptin;
    return d;
  }
};

namespace detail {

// One cuBLASLt matmul configuration (descriptors + the heuristic's algorithm) for a fixed
// problem; built once per shape/dtype/epilogue/alignment and reused, since building it
// costs far more than a small GEMM.
struct LtPlan {
  cublasLtMatmulDesc_t op = nullptr;
  cublasLtMatrixLayout_t a = nullptr, b = nullptr, c = nullptr;
  cublasLtMatmulAlgo_t algo{};
  cublasLtEpilogue_t epilogue = CUBLASLT_EPILOGUE_DEFAULT;  // what cuBLASLt fuses in this plan
  bool fuses_bias() const { return epilogue == CUBLASLT_EPILOGUE_BIAS || epilogue == CUBLASLT_EPILOGUE_GELU_BIAS; }
  bool fuses_gelu() const { return epilogue == CUBLASLT_EPILOGUE_GELU || epilogue == CUBLASLT_EPILOGUE_GELU_BIAS; }
  LtPlan() = default;
  LtPlan(const LtPlan&) = delete;
  LtPlan& operator=(const LtPlan&) = delete;
  ~LtPlan() {
    if (c) cublasLtMatrixLayoutDestroy(c);
    if (b) cublasLtMatrixLayoutDestroy(b);
    if (a) cublasLtMatrixLayoutDestroy(a);
    if (op) cublasLtMatmulDescDestroy(op);
  }
};

// dtype, M, N, K, ldx, ldy, wanted cuBLASLt epilogue, alignment of x, w, y (bytes).
using LtPlanKey = std::array<std::int64_t, 10>;

}  // namespace detail

class Context {
 public:
  static constexpr std::size_t default_workspace_bytes = std::size_t{32} << 20;  // cuBLASLt's advice for Hopper

  // device < 0: the calling thread's current device (0 unless the thread chose another, as a
  // tensor-parallel group's threads do: core/tensor_parallel.hpp).
  explicit Context(int device = -1, std::size_t workspace_bytes = default_workspace_bytes) {
    if (device < 0) EPONA_CUDA_CHECK(cudaGetDevice(&device));
    EPONA_CHECK(has_gpu(), "cuda::Context: no CUDA device is available");
    int count = 0;
    EPONA_CUDA_CHECK(cudaGetDeviceCount(&count));
    EPONA_CHECK(device >= 0 && device < count, "cuda::Context: device ", device, " does not exist (", count,
                " present)");
    EPONA_CUDA_CHECK(cudaSetDevice(device));
    info_ = DeviceInfo::query(device);
    cudaStream_t s = nullptr;
    EPONA_CUDA_CHECK(cudaStreamCreateWithFlags(&s, cudaStreamNonBlocking));
    stream_.reset(s);
    cublasLtHandle_t h = nullptr;
    EPONA_CUBLAS_CHECK(cublasLtCreate(&h));
    lt_.reset(h);
    if (workspace_bytes) {
      void* w = nullptr;
      EPONA_CUDA_CHECK(cudaMalloc(&w, workspace_bytes));
      workspace_.reset(w);
      workspace_bytes_ = workspace_bytes;
    }
  }
  Context(const Context&) = delete;
  Context& operator=(const Context&) = delete;

  cudaStream_t stream() const { return stream_.get(); }
  cublasLtHandle_t lt() const { return lt_.get(); }
  void* workspace() const { return workspace_.get(); }
  std::size_t workspace_bytes() const { return workspace_bytes_; }
  const DeviceInfo& info() const { return info_; }
  // The tuning choices the kernels on this context take (the environment's at construction).
  KernelPolicy& policy() { return policy_; }
  const KernelPolicy& policy() const { return policy_; }

  // Waits for everything queued on the context's stream; surfaces asynchronous kernel faults.
  void synchronize() const { EPONA_CUDA_CHECK(cudaStreamSynchronize(stream())); }

  std::map<detail::LtPlanKey, std::unique_ptr<detail::LtPlan>>& gemm_plans() { return gemm_plans_; }

  // A collective between GPUs that threads of this process drive (nccl_shard_sum.hpp) must be
  // launched by every rank before any rank makes a CUDA call that can wait on a device
  // (cudaMalloc, cudaFree, a pageable copy): that call waits for its GPU's collective, which
  // waits for a rank stuck behind the call (docs/parallel.md, "the group's fences"). A
  // collective enqueued while the stream records a graph leaves its group's `fence` (a barrier
  // of the ranks) here, and the graph then calls it before and after every launch (graph.hpp).
  // A graph recorded by other code must take it here after its capture and do the same.
  void note_captured_collective(std::function<void()> fence) { captured_fence_ = std::move(fence); }
  std::function<void()> take_captured_collective() { return std::exchange(captured_fence_, {}); }

  // Host -> device on the stream without waiting for it, through the context's pinned ring
  // (host_staging.hpp); src may be reused on return. False, with nothing done, where the ring
  // cannot take the copy (too large, the stream capturing a graph, no pinned memory).
  bool upload_staged(void* dst, const void* src, std::size_t bytes) {
    if (!staging_) staging_ = std::make_unique<HostStaging>(stream());
    return staging_->upload(dst, src, bytes);
  }

  // A device buffer of `bytes` kept for the context's lifetime under `name` (constant tables
  // that kernels build on first use, such as the bf16 GELU lookup table). `*created` tells the
  // caller whether it must fill it. The same name must always ask for the same size.
  bool has_constant_table(const std::string& name) const { return tables_.count(name) != 0; }
  void* constant_table(const std::string& name, std::size_t bytes, bool* created) {
    auto& slot = tables_[name];
    *created = !slot.buffer;
    if (*created) {
      void* p = nullptr;
      EPONA_CUDA_CHECK(cudaMalloc(&p, bytes));
      slot.buffer.reset(p);
      slot.bytes = bytes;
    }
    EPONA_CHECK(slot.bytes == bytes, "cuda::Context: constant table '", name, "' asked for ", bytes,
                " bytes, has ", slot.bytes);
    return slot.buffer.get();
  }

 private:
  struct StreamDeleter {
    void operator()(cudaStream_t s) const { cudaStreamDestroy(s); }
  };
  struct LtDeleter {
    void operator()(cublasLtHandle_t h) const { cublasLtDestroy(h); }
  };
  struct DeviceFree {
    void operator()(void* p) const { cudaFree(p); }
  };

  DeviceInfo info_;
  KernelPolicy policy_ = KernelPolicy::from_environment();
  std::unique_ptr<CUstream_st, StreamDeleter> stream_;
  std::unique_ptr<HostStaging> staging_;  // after the stream: its transfers end before the stream goes
  std::unique_ptr<cublasLtContext, LtDeleter> lt_;
  std::unique_ptr<void, DeviceFree> workspace_;
  std::size_t workspace_bytes_ = 0;
  struct Table {
    std::unique_ptr<void, DeviceFree> buffer;
    std::size_t bytes = 0;
  };
  std::map<std::string, Table> tables_;
  std::function<void()> captured_fence_;
  // Declared last so plans are destroyed before the handle they were made with.
  std::map<detail::LtPlanKey, std::unique_ptr<detail::LtPlan>> gemm_plans_;
};

}  // namespace epona::cuda
