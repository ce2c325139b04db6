// example_custom_dit_cuda — examples/custom_dit.hpp's TinyDit, a DiT assembled from the kit's
// blocks, sampled on the GPU and on the CPU from the same seeds: the same model code on both
// backends, and their samples agree (float32 throughout; the bound covers the backends' different
// summation orders over 10 steps). Without a GPU it says so and exits 0.
//
// usage: example_custom_dit_cuda [STEPS]   (default 10)
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "epona/cuda/backend.cuh"
#include "custom_dit.hpp"
#include "epona/cpu/context.hpp"

using namespace epona;

int main(int argc, char** argv) {
  try {
    if (!cuda::has_gpu()) {
      std::printf("no CUDA device: nothing to run\n");
      return 0;
    }
    const std::int64_t steps = example::steps_argument(argc, argv);
    cuda::Context gpu;
    cpu::Context cpu;
    const Tensor<float> on_gpu = example::sample_tiny_dit<Cuda>(gpu, steps, /*seed=*/11);
    const Tensor<float> on_cpu = example::sample_tiny_dit<Cpu>(cpu, steps, /*seed=*/11);
    double diff = 0, ref = 0;
    for (std::int64_t i = 0; i < on_cpu.numel(); ++i) {
      EPONA_CHECK(std::isfinite(on_gpu.data()[i]), "the GPU sample is not finite at ", i);
      diff = std::max(diff, std::abs(double(on_gpu.data()[i]) - double(on_cpu.data()[i])));
      ref = std::max(ref, std::abs(double(on_cpu.data()[i])));
    }
    std::printf("sampled (%lld, %lld) in %lld Euler steps on %s: max |GPU - CPU| / max |CPU| = %.2e\n",
                (long long)on_cpu.size(0), (long long)on_cpu.size(1), (long long)steps, gpu.info().name.c_str(),
                diff / ref);
    EPONA_CHECK(diff <= 1e-4 * ref, "the GPU's sample differs from the CPU's by ", diff / ref, " (bound 1e-4)");
  } catch (const std::exception& e) {
    std::fprintf(stderr, "example_custom_dit_cuda: %s\n", e.what());
    return 1;
  }
}
