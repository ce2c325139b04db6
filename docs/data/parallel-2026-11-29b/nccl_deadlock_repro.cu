// The two-GPU hang of 2026-11-29 reduced to raw CUDA and NCCL (no epona code): one process, one
// thread per GPU, as cuda::NcclShardGroup runs. Rank 0 all-reduces and then makes a CUDA call
// that waits on its GPU; rank 1 first makes such calls (cudaMalloc, pageable copies, cudaFree)
// and only then all-reduces. `fenced` puts a barrier of the two threads before and after each
// all-reduce, as the group now does. Build: nvcc -O2 -std=c++20 nccl_deadlock_repro.cu -lnccl
// Run: NCCL_NVLS_ENABLE=0 ./a.out fenced|unfenced   (prints "done" or hangs)
#include <cuda_runtime.h>
#include <nccl.h>

#include <barrier>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <thread>
#include <vector>

#define OK(x)                                                       \
  do {                                                              \
    auto e_ = (x);                                                  \
    if (e_ != 0) {                                                  \
      std::fprintf(stderr, "%s failed (%d) line %d\n", #x, int(e_), __LINE__); \
      std::exit(1);                                                 \
    }                                                               \
  } while (0)

int main(int argc, char** argv) {
  const bool fenced = argc > 1 && std::strcmp(argv[1], "fenced") == 0;
  int devices[2] = {0, 1};
  ncclComm_t comms[2];
  OK(ncclCommInitAll(comms, 2, devices));
  std::barrier<> fence(2);
  auto rank = [&](int r) {
    OK(cudaSetDevice(r));
    cudaStream_t s;
    OK(cudaStreamCreateWithFlags(&s, cudaStreamNonBlocking));
    float* d = nullptr;
    OK(cudaMalloc(&d, 1 << 20));
    std::vector<float> host(1 << 22, 1.f);
    auto memory_calls = [&] {
      for (int i = 0; i < 8; ++i) {
        void* p = nullptr;
        OK(cudaMalloc(&p, host.size() * 4));
        OK(cudaMemcpy(p, host.data(), host.size() * 4, cudaMemcpyHostToDevice));
        OK(cudaMemcpy(host.data(), p, host.size() * 4, cudaMemcpyDeviceToHost));
        OK(cudaFree(p));
      }
    };
    for (int round = 0; round < 5; ++round) {
      if (r == 1) {
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
        memory_calls();
      }
      if (fenced) fence.arrive_and_wait();
      OK(ncclAllReduce(d, d, 1 << 18, ncclFloat32, ncclSum, comms[r], s));
      if (fenced) fence.arrive_and_wait();
      if (r == 0) memory_calls();
      std::printf("rank %d round %d\n", r, round);
      std::fflush(stdout);
    }
    OK(cudaStreamSynchronize(s));
  };
  std::thread t0(rank, 0), t1(rank, 1);
  t0.join();
  t1.join();
  std::printf("done\n");
  for (auto c : comms) ncclCommDestroy(c);
}
