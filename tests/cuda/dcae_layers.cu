// The DC-AE layers and blocks (nn/conv2d, norm2d, lite_mla, glu_mbconv, dcae_blocks,
// pixel_shuffle, llama_block) run by the same layer code on the GPU (channels-last maps of T)
// and on the CPU (NCHW float maps), with the same random weights (same seed) and inputs.
// Every buffer the GPU layers allocate is poisoned (NaN) when handed out. Bounds: float32
// rel_l2 <= 1e-5 and max <= 1e-5·max|ref|; bf16 (weights bf16 on both sides, inputs rounded to
// bf16) twice the official bf16 recipe's per-stage error: rel_l2 <= 2e-2, max <= 4e-2·max|ref|.
#include <cstdio>
#include <string>
#include <vector>

#include "dcae_testing.cuh"
#include "epona/cuda/backend.cuh"
#include "epona/nn/blocks/dcae_blocks.hpp"
#include "epona/nn/blocks/llama_block.hpp"

using namespace epona;
using namespace epona::test;
using i64 = std::int64_t;

namespace {

std::uint32_t next_seed() {
  static std::uint32_t s = 5000;
  return ++s;
}

// Builds the layer on both backends from `make(backend tag)`, randomises both with one seed,
// runs `forward(layer, ctx, map)` (returning the output map) on the same input, compares.
template <class T, class Make, class Forward>
void compare(const std::string& what, const Shape& nchw, Make make, Forward forward) {
  PoisonBuffers poisoned;
  auto cpu_layer = make(Cpu{});
  auto gpu_layer = make(Cuda{});
  const std::uint64_t seed = next_seed();
  cpu_layer.randomize(seed);
  gpu_layer.randomize(seed);
  HostF x = random_tensor(nchw, next_seed(), -2.f, 2.f);
  round_to<T>(x);
  const HostF ref = forward(cpu_layer, host(), x.clone());
  const HostF out = download_map(gpu(), forward(gpu_layer, gpu(), upload_map<T>(gpu(), x)));
  REQUIRE(out.shape() == ref.shape());
  check_error(measure(out, ref), stage_bound<T>(max_abs(ref)), what + " " + type_name<T>());
}

// Generic forwards: a branch (forward), a residual update (add_to / forward_inplace).
const auto branch = [](auto& layer, auto& ctx, auto x) { return layer.forward(ctx, x); };
const auto in_place = [](auto& layer, auto& ctx, auto x) {
  layer.forward_inplace(ctx, x);
  return x;
};
const auto added = [](auto& layer, auto& ctx, auto x) {
  layer.add_to(ctx, x);
  return x;
};

template <class T>
void all_layers() {
  using nn::Norm2dKind;
  compare<T>("Conv2d 3x3 +bias relu", {2, 16, 9, 13},
             [](auto b) { return nn::Conv2d<decltype(b), T>(16, 24, 3); },
             [](auto& l, auto& ctx, auto x) { return l.forward(ctx, x, ConvAct::Relu); });
  compare<T>("Conv2d 1x1 no bias", {1, 40, 7, 9},
             [](auto b) { return nn::Conv2d<decltype(b), T>(40, 72, 1, 1, false); }, branch);
  compare<T>("Conv2d depthwise 3x3 silu", {1, 64, 7, 9},
             [](auto b) { return nn::Conv2d<decltype(b), T>(64, 64, 3, 64); },
             [](auto& l, auto& ctx, auto x) { return l.forward(ctx, x, ConvAct::Silu); });
  for (const Norm2dKind kind : {Norm2dKind::Rms, Norm2dKind::Batch}) {
    const std::string name = kind == Norm2dKind::Rms ? "RMSNorm2d" : "BatchNorm2d";
    compare<T>(name + " + silu", {2, 64, 5, 7}, [&](auto b) { return nn::Norm2d<decltype(b), T>(kind, 64); },
               [](auto& l, auto& ctx, auto x) {
                 l.forward_inplace(ctx, x, ConvAct::Silu);
                 return x;
               });
    compare<T>(name + " residual add (x += norm(x))", {1, 96, 6, 5},
               [&](auto b) { return nn::Norm2d<decltype(b), T>(kind, 96); },
               [](auto& l, auto& ctx, auto x) {
                 auto branch_copy = nn::copy_of(ctx, x);
                 l.add_to(ctx, branch_copy, x);
                 return x;
               });
  }
  compare<T>("LiteMLA branch, 39 pixels (linear order)", {1, 64, 3, 13},
             [](auto b) { return nn::LiteMLA<decltype(b), T>(64, Norm2dKind::Rms); }, branch);
  compare<T>("LiteMLA branch, 6 pixels (quadratic order)", {2, 96, 2, 3},
             [](auto b) { return nn::LiteMLA<decltype(b), T>(96, Norm2dKind::Rms); }, branch);
  compare<T>("LiteMLA residual", {1, 64, 8, 12},
             [](auto b) { return nn::LiteMLA<decltype(b), T>(64, Norm2dKind::Rms); }, added);
  compare<T>("GLUMBConv branch", {2, 32, 5, 7},
             [](auto b) { return nn::GLUMBConv<decltype(b), T>(32, Norm2dKind::Rms, ConvAct::Silu); }, branch);
  compare<T>("GLUMBConv residual", {1, 32, 8, 12},
             [](auto b) { return nn::GLUMBConv<decltype(b), T>(32, Norm2dKind::Rms, ConvAct::Silu); }, added);
  compare<T>("ResBlock (BatchNorm, ReLU)", {1, 32, 16, 24},
             [](auto b) { return nn::ResBlock<decltype(b), T>(32, Norm2dKind::Batch, ConvAct::Relu); }, in_place);
  {  // the BatchNorm folded into conv2 (default) and, for comparison, the unfused conv -> norm_2d_add
    UseFusion unfused(false);
    compare<T>("ResBlock (BatchNorm, ReLU), unfused", {1, 32, 16, 24},
               [](auto b) { return nn::ResBlock<decltype(b), T>(32, Norm2dKind::Batch, ConvAct::Relu); }, in_place);
  }
  compare<T>("ResBlock (BatchNorm, ReLU), 64 ch, 2 images", {2, 64, 12, 20},
             [](auto b) { return nn::ResBlock<decltype(b), T>(64, Norm2dKind::Batch, ConvAct::Relu); }, in_place);
  compare<T>("ResBlock (RMSNorm, SiLU)", {2, 16, 9, 11},
             [](auto b) { return nn::ResBlock<decltype(b), T>(16, Norm2dKind::Rms, ConvAct::Silu); }, in_place);
  compare<T>("EfficientViTBlock", {1, 64, 6, 10},
             [](auto b) { return nn::EfficientViTBlock<decltype(b), T>(64, Norm2dKind::Rms, ConvAct::Silu); },
             in_place);
  for (const bool shortcut : {true, false}) {
    const std::string s = shortcut ? " with shortcut" : " without shortcut";
    compare<T>("DownsampleBlock 32 -> 64" + s, {1, 32, 8, 14},
               [&](auto b) { return nn::DownsampleBlock<decltype(b), T>(32, 64, shortcut); }, branch);
    compare<T>("UpsampleBlock 64 -> 32" + s, {1, 64, 4, 7},
               [&](auto b) { return nn::UpsampleBlock<decltype(b), T>(64, 32, shortcut); }, branch);
  }
  compare<T>("DownsampleBlock 3 -> 32 (encoder project_in)", {1, 3, 16, 32},
             [](auto b) { return nn::DownsampleBlock<decltype(b), T>(3, 32, false); }, branch);
  compare<T>("UpsampleBlock 32 -> 3 (decoder project_out)", {1, 32, 8, 16},
             [](auto b) { return nn::UpsampleBlock<decltype(b), T>(32, 3, false); }, branch);
}

// The temporal TransformerBlock on rows (clip, frame, token) x 32 in both sequence layouts.
template <class T>
void transformer_blocks() {
  PoisonBuffers poisoned;
  const i64 clips = 2, frames = 3, L = 10, D = 32, rows = clips * frames * L;
  const nn::TokenSequences time{clips, L, frames, 1, L, true}, space{clips, frames, L, L, 1, false};
  for (const auto& [name, seq] : {std::pair{"time (causal)", time}, std::pair{"space", space}}) {
    nn::TransformerBlock<Cpu, T> c(D, 8, 256, 1e-5f, 1000.f);
    nn::TransformerBlock<Cuda, T> g(D, 8, 256, 1e-5f, 1000.f);
    const std::uint64_t seed = next_seed();
    c.randomize(seed);
    g.randomize(seed);
    std::vector<float> cos_t, sin_t;
    nn::rope_table_1d(seq, c.head_dim(), c.rope_theta, cos_t, sin_t);
    const Shape table{rows, c.head_dim() / 2};
    const Dev<float> dcos = upload<float>(gpu(), HostF::view(cos_t.data(), table).clone());
    const Dev<float> dsin = upload<float>(gpu(), HostF::view(sin_t.data(), table).clone());
    HostF x = random_tensor({rows, D}, next_seed(), -2.f, 2.f);
    round_to<T>(x);
    HostF ref = x.clone();
    c.forward_inplace(host(), ref, seq, cos_t.data(), sin_t.data());
    Dev<float> dx = upload<float>(gpu(), x);  // the residual stream is float32 (bf16: GEMMs in bf16)
    g.forward_inplace(gpu(), dx, seq, dcos.data(), dsin.data());
    check_error(measure(download(gpu(), dx), ref), stage_bound<T>(max_abs(ref)),
                std::string("TransformerBlock ") + name + " " + type_name<T>());
  }
}

}  // namespace

TEST_CASE("DC-AE layers and blocks: GPU (channels-last) vs CPU, float32") {
  EPONA_REQUIRE_GPU();
  // float32: Auto is cuBLASLt throughout; cuDNN's FMA path is checked too where it loads.
  std::vector<cuda::ConvEngine> engines{cuda::ConvEngine::Auto};
  if (cuda::cudnn_unavailable(gpu()).empty()) engines.push_back(cuda::ConvEngine::Cudnn);
  for (const auto engine : engines) {
    UseEngine use(engine);
    std::printf("engine %s\n", engine_name(engine));
    all_layers<float>();
  }
}

TEST_CASE("DC-AE layers and blocks: GPU (channels-last) vs CPU, bf16") {
  EPONA_REQUIRE_GPU();
  for (const auto engine : {cuda::ConvEngine::Auto, cuda::ConvEngine::Gemm}) {
    UseEngine use(engine);
    std::printf("engine %s\n", engine_name(engine));
    all_layers<bf16>();
  }
}

TEST_CASE("DC-AE temporal TransformerBlock: GPU vs CPU, both layouts, float32 and bf16") {
  EPONA_REQUIRE_GPU();
  transformer_blocks<float>();
  transformer_blocks<bf16>();
}

TEST_CASE("DC-AE layers name the channels-last layout in their input errors") {
  EPONA_REQUIRE_GPU();
  nn::Conv2d<Cuda, float> conv(3, 4, 3);
  conv.randomize(1);
  const Dev<float> wrong({1, 3, 4, 5});  // NCHW-shaped: 5 channels when read channels-last
  CHECK_THROWS_WITH_AS(conv.forward(gpu(), wrong), doctest::Contains("(N, H, W, 3)"), Error);
  nn::Norm2d<Cuda, float> norm(nn::Norm2dKind::Rms, 3);
  norm.randomize(1);
  Dev<float> x({1, 4, 5, 4});
  CHECK_THROWS_WITH_AS(norm.forward_inplace(gpu(), x), doctest::Contains("RMSNorm2d(3): input must be (N, H, W, 3)"),
                       Error);
  CHECK(conv.weight.shape() == Shape{4, 3, 3, 3});  // [out, k, k, in] on the GPU
}

TEST_CASE("cuDNN state released before exit (and made again on demand)") {
  EPONA_REQUIRE_GPU();
  cuda::release_cudnn();
  CHECK(cuda::cudnn_unavailable(gpu()) == cuda::cudnn_unavailable(gpu()));
  cuda::release_cudnn();
}
