// The DC-AE's temporal front on the GPU through the fused kernels (cuda/conv/dcae_temporal.cuh: one
// kernel per LLaMA block) against the CPU backend's DcaeTemporalBlocks (the reference: plain
// GEMMs, RoPE, attention) with the same seeded weights and inputs, and against the GPU's unfused
// path (EPONA_CUDA_DCAE_FUSE=0's kernels). Sizes: one frame of 16x32 latents (the 512x1024
// decode), clips of 6 frames at 4x9 (causal time attention over 6 frames), odd sizes. Every
// buffer the GPU code allocates is poisoned. Bounds: float32 rel_l2 and max <= 1e-5 (of max|ref|);
// bf16 the DC-AE stage bound (rel_l2 <= 2e-2, max <= 4e-2·max|ref|), and fused vs unfused bf16
// within the same bound (both round the same intermediates to bf16; only accumulation order differs).
#include <array>
#include <cstdio>
#include <string>
#include <vector>

#include "dcae_testing.cuh"
#include "epona/cuda/backend.cuh"
#include "epona/model/dcae.hpp"

using namespace epona;
using namespace epona::test;
using i64 = std::int64_t;

namespace {

template <class T>
void check_temporal(i64 N, i64 h, i64 w, i64 frames, std::uint64_t seed) {
  PoisonBuffers poisoned;
  DcaeConfig cfg;
  DcaeTemporalBlocks<Cpu, T> cpu_blocks(cfg);
  DcaeTemporalBlocks<Cuda, T> gpu_blocks(cfg);
  cpu_blocks.randomize(seed);
  gpu_blocks.randomize(seed);
  HostF z = random_tensor({N, cfg.latent_channels, h, w}, static_cast<std::uint32_t>(seed + 1), -2.f, 2.f);
  round_to<T>(z);
  const HostF ref = cpu_blocks.forward(host(), z.clone(), frames);
  const auto run = [&](bool fused) {
    UseDcaeFusion use(fused);
    const Dev<T> latent = upload_map<T>(gpu(), z);
    return download_map(gpu(), gpu_blocks.forward(gpu(), latent, frames));
  };
  const HostF fused = run(true), unfused = run(false);
  char what[160];
  std::snprintf(what, sizeof what, "temporal fused %lldx%lldx%lld frames %lld %s", (long long)N, (long long)h,
                (long long)w, (long long)frames, type_name<T>());
  check_error(measure(fused, ref), stage_bound<T>(max_abs(ref)), std::string(what) + " vs CPU");
  check_error(measure(fused, unfused), stage_bound<T>(max_abs(unfused)), std::string(what) + " vs unfused GPU");
}

}  // namespace

TEST_CASE("DC-AE temporal blocks fused on the GPU vs the CPU and the unfused GPU path") {
  EPONA_REQUIRE_GPU();
  std::uint64_t seed = 700;
  for (const auto& [N, h, w, frames] : std::vector<std::array<i64, 4>>{
           {1, 16, 32, 1}, {12, 4, 9, 6}, {2, 3, 5, 1}, {6, 2, 7, 3}, {6, 16, 32, 6}}) {
    check_temporal<float>(N, h, w, frames, seed += 10);
    check_temporal<bf16>(N, h, w, frames, seed += 10);
  }
}

TEST_CASE("fused temporal blocks decline other block extents (the caller falls back)") {
  EPONA_REQUIRE_GPU();
  nn::TransformerBlock<Cuda, float> narrow(16, 4, 64, 1e-5f, 1000.f);  // dim 16: not the fused kernel's 32
  narrow.randomize(3);
  struct Step {
    const nn::TransformerBlock<Cuda, float>* block;
    nn::TokenSequences seq;
    const float *cos, *sin;
  };
  const nn::TokenSequences seq{1, 1, 4, 4, 1, false};
  Dev<float> x({4, 16}), table({4, 2});
  const std::vector<Step> steps{{&narrow, seq, table.data(), table.data()}};
  CHECK_FALSE(cuda::fused_transformer_blocks(gpu(), x.data(), 4, steps));
}
