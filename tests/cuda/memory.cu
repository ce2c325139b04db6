// GPU tests for epona/cuda/{check,context,memory,host_staging}.hpp: the context's device info,
// host <-> device copies of float32 and bf16 tensors (bit-exact round trips), device copies and
// fills, staged uploads (they do not wait for the stream, land intact when the ring wraps, and
// step aside where they cannot run), the device arena (alignment, exhaustion, rewind), and that
// CUDA, launch and cuBLASLt failures surface as epona::Error naming the failing call.
#include "cuda_test_util.cuh"

#include <cstring>

using namespace epona;
using namespace epona::test;

namespace {
__global__ void noop_kernel() {}

__device__ std::uint64_t global_ns() {
  std::uint64_t t;
  asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t));
  return t;
}

// Holds its stream until the host sets flag[0], or gives up after two seconds (flag[1] = 1), so
// a host that waits for the stream (or launches that block, as under a sanitizer) cannot hang.
__global__ void wait_for_host_kernel(volatile int* flag) {
  const std::uint64_t start = global_ns();
  while (flag[0] == 0)
    if (global_ns() - start > 2'000'000'000ull) {
      flag[1] = 1;
      return;
    }
}

// Pinned, mapped host flags that a kernel can wait on: [0] raised by the host, [1] the timeout.
struct HostFlag {
  int* host = nullptr;
  int* device = nullptr;
  HostFlag() {
    EPONA_CUDA_CHECK(cudaHostAlloc(&host, 2 * sizeof(int), cudaHostAllocMapped));
    host[0] = host[1] = 0;
    EPONA_CUDA_CHECK(cudaHostGetDevicePointer(reinterpret_cast<void**>(&device), host, 0));
  }
  ~HostFlag() { cudaFreeHost(host); }
  void raise() { reinterpret_cast<volatile int*>(host)[0] = 1; }
  bool timed_out() const { return reinterpret_cast<volatile int*>(host)[1] != 0; }
};

std::vector<unsigned char> pattern(std::size_t n, unsigned seed) {
  std::vector<unsigned char> v(n);
  for (std::size_t i = 0; i < n; ++i) v[i] = static_cast<unsigned char>((i * 131 + seed * 7919) >> 3);
  return v;
}
}  // namespace

TEST_CASE("cuda context reports the device") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const auto& d = ctx.info();
  std::printf("  device %d: %s, sm_%d%d, %d SMs, %.1f GiB, L2 %.1f MiB, smem/block opt-in %zu KiB\n", d.device,
              d.name.c_str(), d.major, d.minor, d.multiprocessors, d.global_bytes / 1073741824.0,
              d.l2_bytes / 1048576.0, d.smem_per_block_optin / 1024);
  CHECK(d.multiprocessors > 0);
  CHECK(!d.name.empty());
  CHECK(ctx.stream() != nullptr);
  CHECK(ctx.lt() != nullptr);
  CHECK(ctx.workspace_bytes() == cuda::Context::default_workspace_bytes);
  CHECK_THROWS_WITH_AS(cuda::Context(1000), doctest::Contains("does not exist"), epona::Error);
}

TEST_CASE_TEMPLATE("cuda host <-> device copies are bit-exact", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  HostF src = random_tensor({7, 143}, 1);
  auto d = upload<T>(ctx, src);
  CHECK(d.shape() == Shape{7, 143});
  Dev<T> d2(d.shape());
  cuda::fill_bytes(ctx, d2, 0xFF);
  cuda::copy(ctx, d2, d);
  const auto back = cuda::to_host(ctx, d2);
  Tensor<T, Cpu> expect(src.shape());
  for (std::int64_t i = 0; i < src.numel(); ++i) expect.data()[i] = T(src.data()[i]);
  CHECK(std::memcmp(back.data(), expect.data(), expect.nbytes()) == 0);

  // Views (slices) copy only their rows.
  auto rows = d2.slice(2, 4);
  const auto part = cuda::to_host(ctx, rows);
  CHECK(std::memcmp(part.data(), expect.data() + 2 * 143, part.nbytes()) == 0);

  Tensor<T, Cpu> wrong({7, 142});
  CHECK_THROWS_WITH_AS(cuda::copy(ctx, wrong, d), doctest::Contains("differ"), epona::Error);
  Dev<T> empty({0, 5});
  CHECK(cuda::to_host(ctx, empty).numel() == 0);
}

TEST_CASE("cuda staged uploads do not wait for the stream") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  HostFlag flag;
  const HostF src = random_tensor({3, 64}, 4);
  Dev<float> dst(src.shape());
  cuda::fill_bytes(ctx, dst, 0xFF);
  wait_for_host_kernel<<<1, 1, 0, ctx.stream()>>>(flag.device);
  EPONA_CUDA_CHECK_LAUNCH();
  const bool launch_blocked = cudaStreamQuery(ctx.stream()) == cudaSuccess;
  cuda::copy_async(ctx, dst, src);  // a pageable copy would wait here for the kernel (its timeout)
  const cudaError_t state = cudaStreamQuery(ctx.stream());
  flag.raise();
  CHECK(measure(cuda::to_host(ctx, dst), src).max_abs == 0);
  if (launch_blocked) {  // the launch itself waited for the kernel (its timeout): nothing to observe
    MESSAGE("kernel launches block the host here (a sanitizer?): only the upload's bytes are checked");
    return;
  }
  CHECK(state == cudaErrorNotReady);  // the kernel still held the stream when the upload returned
  CHECK_FALSE(flag.timed_out());     // ... and ended on the host's flag, raised after the upload
}

TEST_CASE("cuda staged uploads land intact as the ring wraps") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  constexpr std::size_t kRing = 1000, kUploads = 60, kMost = 700;
  cuda::HostStaging staging(ctx.stream(), kRing);
  Dev<unsigned char> dst({static_cast<std::int64_t>(kUploads * kMost)});
  cuda::fill_bytes(ctx, dst, 0xAB);
  std::vector<unsigned char> expect(kUploads * kMost, 0xAB), host;
  for (std::size_t i = 0; i < kUploads; ++i) {
    const std::size_t n = 1 + (i * 389) % kMost;
    host = pattern(n, static_cast<unsigned>(i));
    REQUIRE(staging.upload(dst.data() + i * kMost, host.data(), n));
    std::copy(host.begin(), host.end(), expect.begin() + static_cast<std::ptrdiff_t>(i * kMost));
    std::fill(host.begin(), host.end(), 0);  // the source may be reused at once
  }
  const auto back = cuda::to_host(ctx, dst);
  CHECK(std::memcmp(back.data(), expect.data(), expect.size()) == 0);
}

TEST_CASE("cuda staged uploads step aside where they cannot run") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  cuda::HostStaging staging(ctx.stream(), 256);
  Dev<unsigned char> dst({1024});
  const auto host = pattern(1024, 1);
  CHECK_FALSE(staging.upload(dst.data(), host.data(), 257));  // larger than the ring
  CHECK(staging.upload(dst.data(), host.data(), 0));

  cudaStream_t capture = nullptr;
  EPONA_CUDA_CHECK(cudaStreamCreateWithFlags(&capture, cudaStreamNonBlocking));
  cuda::HostStaging captured(capture, 256);
  cudaGraph_t graph = nullptr;
  EPONA_CUDA_CHECK(cudaStreamBeginCapture(capture, cudaStreamCaptureModeThreadLocal));
  const bool taken = captured.upload(dst.data(), host.data(), 16);  // a graph would replay the ring's later bytes
  EPONA_CUDA_CHECK(cudaStreamEndCapture(capture, &graph));
  CHECK_FALSE(taken);
  if (graph) EPONA_CUDA_CHECK(cudaGraphDestroy(graph));
  EPONA_CUDA_CHECK(cudaStreamDestroy(capture));

  // Through the context, a copy larger than its ring takes the waiting path and still lands.
  const HostF big = random_tensor({static_cast<std::int64_t>(cuda::HostStaging::default_capacity / 4 + 5)}, 6);
  Dev<float> big_dst(big.shape());
  cuda::copy_async(ctx, big_dst, big);
  CHECK(measure(cuda::to_host(ctx, big_dst), big).max_abs == 0);
}

TEST_CASE("cuda device arena hands out aligned views and reports exhaustion") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  cuda::DeviceArena arena(1 << 20);
  auto a = arena.alloc<float>({3, 5});
  auto b = arena.alloc<bf16>({7});
  auto c = arena.alloc<float>({100});
  for (const void* p : {static_cast<const void*>(a.data()), static_cast<const void*>(b.data()),
                        static_cast<const void*>(c.data())})
    CHECK(reinterpret_cast<std::uintptr_t>(p) % 256 == 0);
  CHECK(static_cast<void*>(b.data()) != static_cast<void*>(a.data()));
  const auto mark = arena.mark();
  auto big = arena.alloc<float>({100000});
  CHECK(arena.used() > mark);
  CHECK_THROWS_WITH_AS(arena.alloc<float>({1 << 20}), doctest::Contains("device arena exhausted"), epona::Error);
  arena.rewind(mark);
  auto again = arena.alloc<float>({100000});
  CHECK(again.data() == big.data());
  CHECK(arena.peak() >= arena.used());
  // Arena memory is ordinary device memory: copies work.
  HostF src = random_tensor({3, 5}, 2);
  cuda::copy(ctx, a, src);
  CHECK(measure(cuda::to_host(ctx, a), src).max_abs == 0);
  arena.reset();
  CHECK(arena.used() == 0);
  CHECK_THROWS_AS(arena.rewind(10), epona::Error);
}

TEST_CASE("cuda failures surface as epona::Error naming the call") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  CHECK_THROWS_WITH_AS(EPONA_CUDA_CHECK(cudaSetDevice(100000)), doctest::Contains("cudaSetDevice(100000)"),
                       epona::Error);
  CHECK_THROWS_WITH_AS(EPONA_CUDA_CHECK(cudaSetDevice(100000)), doctest::Contains("memory.cu"), epona::Error);
  EPONA_CUDA_CHECK(cudaSetDevice(0));

  noop_kernel<<<1, 4096, 0, ctx.stream()>>>();  // more threads than a block may have
  CHECK_THROWS_WITH_AS(EPONA_CUDA_CHECK_LAUNCH(), doctest::Contains("kernel launch"), epona::Error);
  noop_kernel<<<1, 32, 0, ctx.stream()>>>();
  EPONA_CUDA_CHECK_LAUNCH();  // the launch error did not stick
  ctx.synchronize();

  // An attribute written with the wrong size is refused (documented INVALID_VALUE).
  cublasLtMatmulDesc_t desc = nullptr;
  EPONA_CUBLAS_CHECK(cublasLtMatmulDescCreate(&desc, CUBLAS_COMPUTE_32F, CUDA_R_32F));
  const char one_byte = 0;
  CHECK_THROWS_WITH_AS(EPONA_CUBLAS_CHECK(cublasLtMatmulDescSetAttribute(desc, CUBLASLT_MATMUL_DESC_TRANSA, &one_byte, 1)),
                       doctest::Contains("CUBLAS_STATUS_INVALID_VALUE"), epona::Error);
  cublasLtMatmulDescDestroy(desc);

  CHECK_THROWS_WITH_AS(Dev<float>({std::int64_t{1} << 48}), doctest::Contains("out of device memory"), epona::Error);
}
