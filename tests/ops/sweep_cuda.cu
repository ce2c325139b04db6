// The op sweep (tests/ops/sweep.hpp) on the CUDA backend: every op against its float64 reference,
// float32 and bf16 (activations are the weight type on the GPU, so bf16 runs under the bf16
// bounds). Outputs are poisoned (all bits set: NaN in float32 and bf16) before each op, so an
// element a kernel fails to write fails its case. Without a GPU it skips with a message. Each op
// prints one line: cases run, worst error and where.
#include "../cuda/cuda_test_util.cuh"
#include "epona/cuda/dcae_ops.cuh"
#include "sweep.hpp"

namespace ops_sweep {

template <> struct Device<epona::Cuda> {
  static constexpr const char* name = "cuda";
  static constexpr bool channels_last = true;  // the DC-AE's maps are (N, H, W, C) on the GPU

  template <class T>
  static epona::Tensor<T, epona::Cuda> upload(epona::cuda::Context& ctx, const std::vector<float>& host) {
    epona::test::HostF t({static_cast<i64>(host.size())});
    std::copy(host.begin(), host.end(), t.data());
    return epona::test::upload<T>(ctx, t);
  }
  template <class T>
  static epona::Tensor<T, epona::Cuda> output(epona::cuda::Context& ctx, i64 n) {
    epona::Tensor<T, epona::Cuda> t({n});
    epona::test::poison(ctx, t);
    return t;
  }
  template <class T>
  static std::vector<float> download(epona::cuda::Context& ctx, const epona::Tensor<T, epona::Cuda>& t) {
    const auto host = epona::test::download(ctx, t);
    return std::vector<float>(host.data(), host.data() + host.numel());
  }
};

}  // namespace ops_sweep

TEST_CASE("op sweep: CUDA, float32") {
  EPONA_REQUIRE_GPU();
  epona::cuda::Context ctx;
  ops_sweep::sweep<epona::Cuda, float>(ctx);
}

TEST_CASE("op sweep: CUDA, bf16") {
  EPONA_REQUIRE_GPU();
  epona::cuda::Context ctx;
  ops_sweep::sweep<epona::Cuda, epona::bf16>(ctx);
}

// Last: the sweep's convolutions made cuDNN's handle, which a static owner would free after
// compute-sanitizer's leak check (a false leak report; docs/cuda.md). Released here, and made
// again on demand.
TEST_CASE("op sweep: cuDNN state released before exit") {
  EPONA_REQUIRE_GPU();
  epona::cuda::Context ctx;
  epona::cuda::release_cudnn();
  CHECK(epona::cuda::cudnn_unavailable(ctx) == epona::cuda::cudnn_unavailable(ctx));
  epona::cuda::release_cudnn();
}

// The one-backend ops (sweep.hpp): the GPU has every GPU-only op in both types (so none is
// skipped by a signature that does not match) and not the CPU's.
static_assert(ops_sweep::HasCudaOnlyOps<epona::cuda::Context, float>);
static_assert(ops_sweep::HasCudaOnlyOps<epona::cuda::Context, epona::bf16>);
static_assert(!ops_sweep::HasSoftmaxRows<epona::cuda::Context, float> && !ops_sweep::HasFill<epona::cuda::Context, float>);
