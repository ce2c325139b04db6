// example_custom_dit — a diffusion transformer of one's own, assembled from the kit's blocks
// (docs/api.md, "Building a model from the blocks"): a token embedding and a condition embedding
// (nn::Linear), a timestep embedding (nn::MlpEmbedder), and a trunk of 2 double-stream and 2
// single-stream FLUX blocks with its final layer (nn::DitTrunk), sampled from noise by the
// rectified-flow Euler solver. The model is custom_dit.hpp's TinyDit, about 40 lines; random
// weights here (its bind() takes a checkpoint's). example_custom_dit_cuda runs it on a GPU.
//
// usage: example_custom_dit [STEPS]   (default 10)
#include <cmath>
#include <cstdio>
#include <string>

#include "custom_dit.hpp"
#include "epona/cpu/context.hpp"

using namespace epona;

int main(int argc, char** argv) {
  try {
    const std::int64_t steps = example::steps_argument(argc, argv);
    const auto params = example::TinyDit<Cpu, float>().parameters();
    std::printf("TinyDit: %.0f parameters in %zu tensors\n", params.count(), params.entries().size());
    cpu::Context ctx;
    const Tensor<float> x = example::sample_tiny_dit<Cpu>(ctx, steps, /*seed=*/11);
    double sum = 0, sq = 0;
    for (std::int64_t i = 0; i < x.numel(); ++i) sum += x.data()[i], sq += double(x.data()[i]) * x.data()[i];
    const double mean = sum / double(x.numel()), rms = std::sqrt(sq / double(x.numel()));
    EPONA_CHECK(std::isfinite(mean) && std::isfinite(rms), "the sample is not finite");
    std::printf("sampled (%lld, %lld) in %lld Euler steps: mean %.4f, rms %.4f\n", (long long)x.size(0),
                (long long)x.size(1), (long long)steps, mean, rms);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "example_custom_dit: %s\n", e.what());
    return 1;
  }
}
