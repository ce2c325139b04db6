// Tests for epona/nn/blocks/glu_mbconv.hpp and epona/nn/blocks/dcae_blocks.hpp against float64 compositions
// of the spec's formulas (§3.7, §4): GLUMBConv (expansion + act, depthwise, value·act(gate),
// projection + norm), EfficientViTBlock (x + LiteMLA(x), then + GLUMBConv), ResBlock with
// RMSNorm2d+SiLU and BatchNorm2d+ReLU, the down/up-sampling pairs with and without shortcut, and
// their official parameter names. Tolerance rel <= 1e-5.
#include <doctest/doctest.h>

#include <set>

#include "dcae_reference.hpp"
#include "epona/nn/blocks/dcae_blocks.hpp"

using namespace epona;
using dcae_ref::HostTensor;
using dcae_ref::i64;
using dcae_ref::Vec;

namespace {

Vec act_ref(Vec v, ConvAct a) {
  for (auto& e : v) e = a == ConvAct::Relu ? dcae_ref::relu(e) : a == ConvAct::Silu ? dcae_ref::silu(e) : e;
  return v;
}

Vec norm_ref(const Vec& x, i64 N, i64 C, i64 HW, const nn::Norm2d<Cpu, float>& n) {
  if (n.kind == nn::Norm2dKind::Rms)
    return dcae_ref::rms_norm_2d(x, N, C, HW, dcae_ref::to_vec(n.weight), dcae_ref::to_vec(n.bias), 1e-5);
  Vec y(x.size());
  for (i64 i = 0; i < N * C; ++i)
    for (i64 p = 0; p < HW; ++p) {
      const i64 c = i % C;
      y[i * HW + p] = (x[i * HW + p] - n.running_mean.data()[c]) / std::sqrt(double(n.running_var.data()[c]) + 1e-5) *
                          n.weight.data()[c] + n.bias.data()[c];
    }
  return y;
}

Vec conv_ref(const Vec& x, i64 N, i64 H, i64 W, const nn::Conv2d<Cpu, float>& c) {
  const Vec b = c.has_bias ? dcae_ref::to_vec(c.bias) : Vec{};
  return dcae_ref::conv2d(x, N, c.in_channels, H, W, dcae_ref::to_vec(c.weight), c.has_bias ? &b : nullptr,
                          c.out_channels, c.kernel, c.groups);
}

Vec add(Vec a, const Vec& b) {
  for (std::size_t i = 0; i < a.size(); ++i) a[i] += b[i];
  return a;
}

Vec glu_ref(const Vec& x, i64 N, i64 H, i64 W, const nn::GLUMBConv<Cpu, float>& g) {
  const i64 HW = H * W, hid = g.hidden;
  const Vec t = conv_ref(act_ref(conv_ref(x, N, H, W, g.inverted_conv), g.act), N, H, W, g.depth_conv);
  Vec gated(static_cast<std::size_t>(N * hid * HW));
  for (i64 n = 0; n < N; ++n)
    for (i64 c = 0; c < hid; ++c)
      for (i64 p = 0; p < HW; ++p) {
        const double a = t[(n * 2 * hid + c) * HW + p], gate = t[(n * 2 * hid + hid + c) * HW + p];
        gated[(n * hid + c) * HW + p] = a * act_ref({gate}, g.act)[0];
      }
  return norm_ref(conv_ref(gated, N, H, W, g.point_conv), N, g.channels, HW, g.point_norm);
}

// Names (with shapes) a module asks for.
struct NameCollector {
  std::set<std::string> names;
  template <class T, class B>
  void param(const std::string& n, Tensor<T, B>&, const Shape& s) { names.insert(n + shape_str(s)); }
  void counter(const std::string& n) { names.insert(n); }
};

template <class M>
std::set<std::string> param_names(M& m, const std::string& prefix) {
  NameCollector v;
  m.visit_params(prefix, v);
  return v.names;
}

}  // namespace

TEST_CASE("GLUMBConv: SiLU after the expansion, none after the depthwise conv, value · SiLU(gate)") {
  cpu::Context ctx;
  const i64 C = 6, N = 2, H = 5, W = 7;
  nn::GLUMBConv<Cpu, float> glu(C, nn::Norm2dKind::Rms, ConvAct::Silu);
  glu.randomize(1);
  const HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 2);
  CHECK(dcae_ref::rel_max(glu.forward(ctx, x), glu_ref(dcae_ref::to_vec(x), N, H, W, glu)) <= 1e-5);
  CHECK(param_names(glu, "m.") ==
        std::set<std::string>{"m.inverted_conv.conv.weight(48, 6, 1, 1)", "m.inverted_conv.conv.bias(48,)",
                              "m.depth_conv.conv.weight(48, 1, 3, 3)", "m.depth_conv.conv.bias(48,)",
                              "m.point_conv.conv.weight(6, 24, 1, 1)", "m.point_conv.norm.weight(6,)",
                              "m.point_conv.norm.bias(6,)"});
}

TEST_CASE("EfficientViTBlock: x + LiteMLA(x), then + GLUMBConv") {
  cpu::Context ctx;
  const i64 C = 64, N = 1, H = 3, W = 13;  // 39 positions: linear attention order
  nn::EfficientViTBlock<Cpu, float> block(C, nn::Norm2dKind::Rms, ConvAct::Silu);
  block.randomize(3);
  HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 4);
  const Vec x0 = dcae_ref::to_vec(x);
  const auto& mla = block.context;
  const Vec qkv = conv_ref(x0, N, H, W, mla.qkv);
  const Vec att = dcae_ref::relu_linear_attention(qkv, N, C / 32, 32, H * W, 1e-15);
  const Vec x1 = add(x0, norm_ref(conv_ref(att, N, H, W, mla.proj_conv), N, C, H * W, mla.proj_norm));
  const Vec ref = add(x1, glu_ref(x1, N, H, W, block.local));
  block.forward_inplace(ctx, x);
  CHECK(dcae_ref::rel_max(x, ref) <= 1e-5);
  const auto names = param_names(block, "s.0.");
  CHECK(names.count("s.0.context_module.main.qkv.conv.weight(192, 64, 1, 1)"));
  CHECK(names.count("s.0.context_module.main.proj.norm.bias(64,)"));
  CHECK(names.count("s.0.local_module.main.depth_conv.conv.weight(512, 1, 3, 3)"));
  CHECK(names.size() == 11);
}

TEST_CASE("ResBlock: x + norm(conv2(act(conv1(x)))) with RMSNorm2d+SiLU and BatchNorm2d+ReLU") {
  cpu::Context ctx;
  const i64 C = 5, N = 2, H = 6, W = 9;
  for (auto [kind, act] : {std::pair{nn::Norm2dKind::Rms, ConvAct::Silu}, {nn::Norm2dKind::Batch, ConvAct::Relu}}) {
    nn::ResBlock<Cpu, float> block(C, kind, act);
    block.randomize(5);
    HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 6);
    const Vec x0 = dcae_ref::to_vec(x);
    const Vec h = act_ref(conv_ref(x0, N, H, W, block.conv1), act);
    const Vec ref = add(x0, norm_ref(conv_ref(h, N, H, W, block.conv2), N, C, H * W, block.norm));
    block.forward_inplace(ctx, x);
    CHECK(dcae_ref::rel_max(x, ref) <= 1e-5);
    const auto names = param_names(block, "p.");
    CHECK(names.count("p.main.conv1.conv.bias(5,)"));
    CHECK(!names.count("p.main.conv2.conv.bias(5,)"));  // conv2 has no bias
    CHECK(names.count("p.main.conv2.norm.weight(5,)"));
    CHECK(names.count("p.main.conv2.norm.num_batches_tracked") == (kind == nn::Norm2dKind::Batch));
  }
}

TEST_CASE("downsample pair: unshuffle(conv 3x3 -> C_out/4) + channel averaging shortcut") {
  cpu::Context ctx;
  const i64 N = 2, C = 8, Co = 16, H = 6, W = 10;
  for (bool shortcut : {true, false}) {
    nn::DownsampleBlock<Cpu, float> down(C, Co, shortcut);
    down.randomize(7);
    const HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 8);
    const Vec x0 = dcae_ref::to_vec(x);
    Vec ref = dcae_ref::unshuffle(conv_ref(x0, N, H, W, down.conv), N, Co / 4, H, W, 2);
    if (shortcut) ref = add(ref, dcae_ref::average_shortcut(x0, N, C, H, W, 2, Co));
    CHECK(dcae_ref::rel_max(down.forward(ctx, x), ref) <= 1e-5);
    CHECK(param_names(down, "d.").count(shortcut ? "d.main.conv.conv.weight(4, 8, 3, 3)" : "d.conv.conv.weight(4, 8, 3, 3)"));
  }
}

TEST_CASE("upsample pair: shuffle(conv 3x3 -> 4·C_out) + channel duplicating shortcut") {
  cpu::Context ctx;
  const i64 N = 2, C = 8, Co = 4, H = 3, W = 5;
  for (bool shortcut : {true, false}) {
    nn::UpsampleBlock<Cpu, float> up(C, Co, shortcut);
    up.randomize(9);
    const HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 10);
    const Vec x0 = dcae_ref::to_vec(x);
    Vec ref = dcae_ref::shuffle(conv_ref(x0, N, H, W, up.conv), N, 4 * Co, H, W, 2);
    if (shortcut) ref = add(ref, dcae_ref::duplicate_shortcut(x0, N, C, H, W, 2, Co));
    CHECK(dcae_ref::rel_max(up.forward(ctx, x), ref) <= 1e-5);
    CHECK(param_names(up, "u.").count(shortcut ? "u.main.conv.conv.bias(16,)" : "u.conv.conv.bias(16,)"));
  }
}
