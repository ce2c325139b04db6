// Tests for epona/cpu/conv.hpp conv2d and epona/nn/conv2d.hpp against a float64 loop written
// from the definition (cross-correlation, zero padding k/2): 3x3 / 1x1 / 5x5 kernels, groups,
// depthwise, widths that are no multiple of any SIMD width, images split over several im2col
// panels, bf16 weights, fused ReLU/SiLU, the Winograd F(2x2, 3x3) path of large 3x3 convs and
// its tile edges, binding by name, and refused geometries.
// Tolerance: rel_max <= 2e-6 (float32 accumulation of at most ~600 terms against float64).
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>

#include "dcae_reference.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/nn/conv2d.hpp"

using namespace epona;
using dcae_ref::HostTensor;
using dcae_ref::i64;

namespace {

struct Case {
  i64 N, C, H, W, O, k, groups;
};

// Runs conv2d on random data and returns rel_max against the float64 loop (act applied to both).
double conv_error(const Case& c, ConvAct act = ConvAct::None, bool with_bias = true, int threads = 0) {
  cpu::Context ctx(threads);
  const HostTensor x = dcae_ref::random_tensor({c.N, c.C, c.H, c.W}, 1);
  const HostTensor w = dcae_ref::random_tensor({c.O, c.C / c.groups, c.k, c.k}, 2);
  const HostTensor b = dcae_ref::random_tensor({c.O}, 3);
  HostTensor y({c.N, c.O, c.H, c.W});
  cpu::conv2d(ctx, x.data(), w.data(), with_bias ? b.data() : nullptr, y.data(),
              Conv2dShape{c.N, c.C, c.H, c.W, c.O, c.k, c.groups}, act);
  const auto bias = dcae_ref::to_vec(b);
  auto ref = dcae_ref::conv2d(dcae_ref::to_vec(x), c.N, c.C, c.H, c.W, dcae_ref::to_vec(w), with_bias ? &bias : nullptr,
                              c.O, c.k, c.groups);
  for (auto& v : ref) v = act == ConvAct::Relu ? dcae_ref::relu(v) : act == ConvAct::Silu ? dcae_ref::silu(v) : v;
  return dcae_ref::rel_max(y, ref);
}

}  // namespace

TEST_CASE("conv2d 3x3 / 1x1 / 5x5, odd sizes, batch > 1") {
  for (const Case& c : {Case{2, 5, 6, 11, 7, 3, 1}, Case{2, 13, 7, 9, 3, 1, 1}, Case{1, 3, 9, 17, 4, 5, 1},
                        Case{1, 3, 1, 1, 2, 3, 1}, Case{1, 2, 2, 3, 5, 5, 1}}) {
    INFO("C=" << c.C << " O=" << c.O << " k=" << c.k << " H=" << c.H << " W=" << c.W);
    CHECK(conv_error(c) <= 2e-6);
  }
}

TEST_CASE("conv2d groups and depthwise") {
  CHECK(conv_error({2, 4, 5, 7, 6, 3, 2}) <= 2e-6);     // 2 groups of 2 -> 3
  CHECK(conv_error({1, 6, 4, 5, 6, 3, 6}) <= 2e-6);     // depthwise (GLUMBConv's depth_conv)
  CHECK(conv_error({2, 33, 9, 19, 33, 3, 33}) <= 2e-6);  // depthwise, tails
  CHECK(conv_error({1, 4, 3, 3, 8, 1, 4}) <= 2e-6);     // grouped 1x1, 2 outputs per group
  CHECK(conv_error({1, 6, 5, 5, 6, 5, 6}) <= 2e-6);     // depthwise 5x5 (padding 2)
}

TEST_CASE("conv2d cut into tasks: row blocks with a remainder, channel blocks on small maps") {
  // K = 64·9 = 576 and W = 128: 14 rows per 4 MB panel, 120 rows = 8 x 14 + 8.
  for (int threads : {1, 2, 3}) {
    INFO("threads = " << threads);
    CHECK(conv_error({1, 64, 120, 128, 8, 3, 1}, ConvAct::None, true, threads) <= 2e-6);
    // 2x3 map, 40 outputs: one row block, output channels split 16 + 16 + 8 (threads > 1)
    CHECK(conv_error({2, 24, 2, 3, 40, 3, 1}, ConvAct::Silu, true, threads) <= 2e-6);
    CHECK(conv_error({2, 24, 2, 3, 40, 1, 1}, ConvAct::Relu, true, threads) <= 2e-6);
    CHECK(conv_error({1, 8, 37, 5, 36, 1, 2}, ConvAct::None, true, threads) <= 2e-6);
  }
}

TEST_CASE("conv2d fused activations, no bias") {
  CHECK(conv_error({1, 5, 6, 7, 4, 3, 1}, ConvAct::Relu) <= 2e-6);
  CHECK(conv_error({1, 5, 6, 7, 4, 3, 1}, ConvAct::Silu) <= 2e-6);
  CHECK(conv_error({1, 6, 6, 7, 6, 3, 6}, ConvAct::Silu) <= 2e-6);
  CHECK(conv_error({1, 5, 6, 7, 4, 3, 1}, ConvAct::None, false) <= 2e-6);
}

TEST_CASE("conv2d with bf16 weights equals the float conv of the rounded weights") {
  // 3x3, 1x1 (LiteMLA / GLUMBConv projections: bf16 widened while packing), grouped, depthwise.
  cpu::Context ctx;
  for (const Case& c : {Case{1, 6, 5, 9, 4, 3, 1}, Case{2, 24, 3, 7, 40, 1, 1}, Case{1, 8, 5, 6, 12, 3, 2},
                        Case{1, 6, 4, 5, 6, 3, 6}}) {
    INFO("C=" << c.C << " O=" << c.O << " k=" << c.k << " groups=" << c.groups);
    const HostTensor x = dcae_ref::random_tensor({c.N, c.C, c.H, c.W}, 4);
    const HostTensor wf = dcae_ref::random_tensor({c.O, c.C / c.groups, c.k, c.k}, 5);
    Tensor<bf16, Cpu> wb(wf.shape());
    HostTensor wr(wf.shape());
    for (i64 i = 0; i < wf.numel(); ++i) wb.data()[i] = bf16(wf.data()[i]), wr.data()[i] = float(wb.data()[i]);
    HostTensor y({c.N, c.O, c.H, c.W});
    cpu::conv2d(ctx, x.data(), wb.data(), nullptr, y.data(), Conv2dShape{c.N, c.C, c.H, c.W, c.O, c.k, c.groups});
    const auto ref =
        dcae_ref::conv2d(dcae_ref::to_vec(x), c.N, c.C, c.H, c.W, dcae_ref::to_vec(wr), nullptr, c.O, c.k, c.groups);
    CHECK(dcae_ref::rel_max(y, ref) <= 2e-6);
  }
}

TEST_CASE("conv2d 3x3 with many channels (Winograd F(2x2, 3x3) unless EPONA_CPU_CONV=direct)") {
  // >= 64 input and output channels and >= 64 tiles of 2x2 pixels: the Winograd path. Odd
  // heights/widths (a half-empty last tile row/column), batch > 1, fused activations, threads.
  // Measured rel_max 3e-7..7e-7 (the direct path: 3e-7..4e-7); the limit stays the direct one's.
  for (int threads : {1, 3}) {
    INFO("threads = " << threads);
    CHECK(conv_error({1, 64, 16, 16, 64, 3, 1}, ConvAct::None, true, threads) <= 2e-6);
    CHECK(conv_error({2, 96, 17, 23, 80, 3, 1}, ConvAct::Relu, true, threads) <= 2e-6);
    CHECK(conv_error({1, 256, 12, 21, 72, 3, 1}, ConvAct::Silu, false, threads) <= 2e-6);
  }
}

TEST_CASE("Winograd F(2x2, 3x3) itself: tile edges, few channels, bf16 weights") {
  // Called directly (whatever EPONA_CPU_CONV says), on every size from 1x1 up: every way a 2x2
  // tile can hang over the map's edge, and channel counts below the kernels' tiles.
  const cpu::gemm::KernelFamily* f = cpu::detail::kernel_family<float>(cpu::active_isa(), 64);
  if (!f) {
    MESSAGE("generic (Eigen) kernels: Winograd does not run on this path");
    return;
  }
  cpu::Context ctx(2);
  for (const Case& c : {Case{1, 3, 1, 1, 5, 3, 1}, Case{1, 4, 2, 3, 7, 3, 1}, Case{1, 5, 3, 2, 9, 3, 1},
                        Case{1, 17, 7, 9, 33, 3, 1}, Case{1, 40, 10, 31, 15, 3, 1}}) {
    INFO("C=" << c.C << " O=" << c.O << " H=" << c.H << " W=" << c.W);
    const HostTensor x = dcae_ref::random_tensor({1, c.C, c.H, c.W}, 11);
    const HostTensor wf = dcae_ref::random_tensor({c.O, c.C, 3, 3}, 12);
    const HostTensor b = dcae_ref::random_tensor({c.O}, 13);
    Tensor<bf16, Cpu> wb(wf.shape());
    HostTensor wr(wf.shape());
    for (i64 i = 0; i < wf.numel(); ++i) wb.data()[i] = bf16(wf.data()[i]), wr.data()[i] = float(wb.data()[i]);
    const auto bias = dcae_ref::to_vec(b);
    auto ref = dcae_ref::conv2d(dcae_ref::to_vec(x), 1, c.C, c.H, c.W, dcae_ref::to_vec(wf), &bias, c.O, 3, 1);
    for (auto& v : ref) v = dcae_ref::relu(v);
    HostTensor y({1, c.O, c.H, c.W});
    std::fill_n(y.data(), y.numel(), std::nanf(""));  // every output must be written
    cpu::winograd::conv3x3(*f, ctx.threads(), x.data(), c.C, c.H, c.W, wf.data(), b.data(), c.O, y.data(),
                           cpu::conv_detail::Relu{});
    CHECK(dcae_ref::rel_max(y, ref) <= 2e-6);
    // bf16 weights: the float Winograd conv of the rounded weights, no activation, no bias
    const auto ref_b = dcae_ref::conv2d(dcae_ref::to_vec(x), 1, c.C, c.H, c.W, dcae_ref::to_vec(wr), nullptr, c.O, 3, 1);
    cpu::winograd::conv3x3(*f, 1, x.data(), c.C, c.H, c.W, wb.data(), nullptr, c.O, y.data(), cpu::detail::Identity{});
    CHECK(dcae_ref::rel_max(y, ref_b) <= 2e-6);
  }
}

TEST_CASE("conv2d refuses geometries it cannot compute") {
  cpu::Context ctx;
  float buf[64] = {};
  CHECK_THROWS_WITH_AS(cpu::conv2d(ctx, buf, buf, nullptr, buf, Conv2dShape{1, 2, 2, 2, 2, 2, 1}),
                       doctest::Contains("odd"), Error);
  CHECK_THROWS_WITH_AS(cpu::conv2d(ctx, buf, buf, nullptr, buf, Conv2dShape{1, 3, 2, 2, 2, 1, 2}),
                       doctest::Contains("groups"), Error);
  CHECK_THROWS_WITH_AS(cpu::conv2d(ctx, buf, buf, nullptr, buf, Conv2dShape{1, 0, 2, 2, 2, 1, 1}),
                       doctest::Contains("bad geometry"), Error);
}

TEST_CASE("nn::Conv2d binds `weight`/`bias` by name and checks its input") {
  cpu::Context ctx;
  HostTensor w = dcae_ref::random_tensor({4, 3, 3, 3}, 6), b = dcae_ref::random_tensor({4}, 7);
  io::TensorMap map("test.safetensors");
  auto raw = [](const HostTensor& t) {
    return io::RawTensor{DType::F32, t.shape(), {reinterpret_cast<const std::byte*>(t.data()), t.nbytes()}};
  };
  map.add("layer.conv.weight", raw(w));
  map.add("layer.conv.bias", raw(b));

  nn::Conv2d<Cpu, float> conv(3, 4, 3);
  io::BindReport report(map);
  conv.bind(map, "layer.conv.", report);
  CHECK_NOTHROW(report.finish());
  const HostTensor x = dcae_ref::random_tensor({1, 3, 4, 5}, 8);
  const HostTensor y = conv.forward(ctx, x);
  const auto bias = dcae_ref::to_vec(b);
  CHECK(dcae_ref::rel_max(y, dcae_ref::conv2d(dcae_ref::to_vec(x), 1, 3, 4, 5, dcae_ref::to_vec(w), &bias, 4, 3, 1)) <=
        2e-6);
  CHECK_THROWS_WITH_AS(conv.forward(ctx, dcae_ref::random_tensor({1, 2, 4, 5}, 9)), doctest::Contains("(N, 3, H, W)"),
                       Error);

  nn::Conv2d<Cpu, float> wrong(3, 5, 3);  // 5 outputs: both tensors mis-shaped
  io::BindReport bad(map);
  wrong.bind(map, "layer.conv.", bad);
  CHECK_THROWS_WITH_AS(bad.finish(), doctest::Contains("'layer.conv.weight' has shape (4, 3, 3, 3), expected (5, 3, 3, 3)"),
                       Error);
  nn::Conv2d<Cpu, float> missing(3, 4, 3);
  io::BindReport absent(map);
  missing.bind(map, "other.", absent);
  CHECK_THROWS_WITH_AS(absent.finish(false), doctest::Contains("missing 'other.weight'"), Error);
}
