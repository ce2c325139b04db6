// benchmarks/gpu_nccl.cu — what splitting one model over the GPUs of a host would pay in
// collectives (issue #40): NCCL all-reduce (tensor parallelism: a block's output summed over the
// GPUs holding its heads and MLP columns) and all-gather (sequence parallelism: every GPU's keys
// and values of its share of the rows) at the VisDiT's sizes (1027 rows x D 2048, bf16) and a
// sweep of sizes, one process driving every GPU (ncclCommInitAll). Per size: the median over
// rounds of the mean of `iters` back-to-back collectives, timed with events on GPU 0 after every
// GPU's stream has finished; algorithm bandwidth = bytes of the full tensor / time.
//   bench_gpu_nccl [--gpus N] [--rounds R] [--iters I]
// Prints one JSON line per measurement. Keep NVLink multicast off (NCCL_NVLS_ENABLE=0), as the
// device README requires; the program refuses to run with it on.
#include <nccl.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include <cuda_runtime.h>

#include "epona/cuda/runtime/check.hpp"

namespace {

#define NCCL_OK(expr)                                                                               \
  do {                                                                                              \
    const ncclResult_t r_ = (expr);                                                                 \
    if (r_ != ncclSuccess) {                                                                        \
      std::fprintf(stderr, "bench_gpu_nccl: %s failed: %s\n", #expr, ncclGetErrorString(r_));      \
      std::exit(1);                                                                                 \
    }                                                                                               \
  } while (0)

struct Gpus {
  int n = 0;
  std::vector<ncclComm_t> comms;
  std::vector<cudaStream_t> streams;
  std::vector<void*> send, recv;
  std::size_t capacity = 0;  // bytes of each buffer
};

Gpus open_gpus(int n, std::size_t capacity) {
  Gpus g;
  g.n = n, g.capacity = capacity;
  g.comms.resize(std::size_t(n));
  std::vector<int> devices(static_cast<std::size_t>(n));
  for (int d = 0; d < n; ++d) devices[std::size_t(d)] = d;
  NCCL_OK(ncclCommInitAll(g.comms.data(), n, devices.data()));
  for (int d = 0; d < n; ++d) {
    EPONA_CUDA_CHECK(cudaSetDevice(d));
    cudaStream_t s = nullptr;
    EPONA_CUDA_CHECK(cudaStreamCreateWithFlags(&s, cudaStreamNonBlocking));
    g.streams.push_back(s);
    void *a = nullptr, *b = nullptr;
    EPONA_CUDA_CHECK(cudaMalloc(&a, capacity));
    EPONA_CUDA_CHECK(cudaMalloc(&b, capacity));
    EPONA_CUDA_CHECK(cudaMemset(a, 0, capacity));  // zeros: bf16 sums stay finite
    g.send.push_back(a), g.recv.push_back(b);
  }
  return g;
}

enum class Op { all_reduce, all_gather };

// One collective on every GPU: all-reduce of `bytes` (the full tensor on each GPU), or all-gather
// of bytes / n from each GPU into the full `bytes`.
void collective(Gpus& g, Op op, std::size_t bytes) {
  const std::size_t elems = bytes / 2;  // bf16
  NCCL_OK(ncclGroupStart());
  for (int d = 0; d < g.n; ++d) {
    const auto i = std::size_t(d);
    if (op == Op::all_reduce)
      NCCL_OK(ncclAllReduce(g.send[i], g.recv[i], elems, ncclBfloat16, ncclSum, g.comms[i], g.streams[i]));
    else
      NCCL_OK(ncclAllGather(g.send[i], g.recv[i], elems / std::size_t(g.n), ncclBfloat16, g.comms[i], g.streams[i]));
  }
  NCCL_OK(ncclGroupEnd());
}

// Milliseconds per collective: the median over rounds of (time of `iters` in a row) / iters.
double time_ms(Gpus& g, Op op, std::size_t bytes, int rounds, int iters) {
  for (int w = 0; w < 5; ++w) collective(g, op, bytes);
  for (int d = 0; d < g.n; ++d) EPONA_CUDA_CHECK(cudaStreamSynchronize(g.streams[std::size_t(d)]));
  std::vector<double> ms;
  EPONA_CUDA_CHECK(cudaSetDevice(0));
  cudaEvent_t start = nullptr, stop = nullptr;
  EPONA_CUDA_CHECK(cudaEventCreate(&start));
  EPONA_CUDA_CHECK(cudaEventCreate(&stop));
  for (int r = 0; r < rounds; ++r) {
    EPONA_CUDA_CHECK(cudaSetDevice(0));
    EPONA_CUDA_CHECK(cudaEventRecord(start, g.streams[0]));
    for (int i = 0; i < iters; ++i) collective(g, op, bytes);
    EPONA_CUDA_CHECK(cudaSetDevice(0));
    EPONA_CUDA_CHECK(cudaEventRecord(stop, g.streams[0]));
    for (int d = 0; d < g.n; ++d) EPONA_CUDA_CHECK(cudaStreamSynchronize(g.streams[std::size_t(d)]));
    float t = 0;
    EPONA_CUDA_CHECK(cudaEventElapsedTime(&t, start, stop));
    ms.push_back(double(t) / iters);
  }
  cudaEventDestroy(start), cudaEventDestroy(stop);
  std::sort(ms.begin(), ms.end());
  return ms[ms.size() / 2];
}

int arg(int argc, char** argv, const char* name, int fallback) {
  for (int i = 1; i + 1 < argc; ++i)
    if (std::strcmp(argv[i], name) == 0) return std::max(1, std::atoi(argv[i + 1]));
  return fallback;
}

}  // namespace

int main(int argc, char** argv) {
  int count = 0;
  if (cudaGetDeviceCount(&count) != cudaSuccess || count < 2) {
    std::printf("bench_gpu_nccl: skipped: %d GPU(s); the collectives need at least 2\n", count);
    return 0;
  }
  const char* nvls = std::getenv("NCCL_NVLS_ENABLE");
  if (!nvls || std::strcmp(nvls, "0") != 0) {
    std::fprintf(stderr, "bench_gpu_nccl: set NCCL_NVLS_ENABLE=0 (NVLink multicast stays off on these machines)\n");
    return 1;
  }
  const int n = std::min(count, arg(argc, argv, "--gpus", count));
  const int rounds = arg(argc, argv, "--rounds", 11), iters = arg(argc, argv, "--iters", 50);
  int version = 0;
  ncclGetVersion(&version);
  cudaDeviceProp prop{};
  EPONA_CUDA_CHECK(cudaGetDeviceProperties(&prop, 0));
  std::printf("{\"device\": \"%s\", \"gpus\": %d, \"nccl\": %d, \"rounds\": %d, \"iters\": %d}\n", prop.name, n,
              version, rounds, iters);
  constexpr std::size_t rows = 1027, width = 2048, bf16 = 2;  // the VisDiT's joint rows and hidden size
  struct Case {
    const char* name;
    Op op;
    std::size_t bytes;
  };
  std::vector<Case> cases = {
      {"visdit_block_output_all_reduce", Op::all_reduce, rows * width * bf16},        // tensor parallel, per sum
      {"visdit_keys_values_all_gather", Op::all_gather, rows * 2 * width * bf16},     // sequence parallel, per block
  };
  for (std::size_t b = std::size_t{8} << 10; b <= std::size_t{64} << 20; b *= 4) {
    cases.push_back({"sweep_all_reduce", Op::all_reduce, b});
    cases.push_back({"sweep_all_gather", Op::all_gather, b});
  }
  std::size_t capacity = 0;
  for (const auto& c : cases) capacity = std::max(capacity, c.bytes);
  Gpus g = open_gpus(n, capacity);
  for (const auto& c : cases) {
    const std::size_t bytes = c.bytes / (2 * std::size_t(n)) * (2 * std::size_t(n));  // whole bf16 shares
    const double ms = time_ms(g, c.op, bytes, rounds, iters);
    std::printf("{\"name\": \"%s\", \"bytes\": %zu, \"us\": %.2f, \"algbw_GBps\": %.1f}\n", c.name, bytes, ms * 1e3,
                double(bytes) / (ms * 1e-3) / 1e9);
    std::fflush(stdout);
  }
  for (int d = 0; d < n; ++d) ncclCommDestroy(g.comms[std::size_t(d)]);
  return 0;
}
