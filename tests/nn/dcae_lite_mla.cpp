// Tests for LiteMLA (epona/nn/blocks/lite_mla.hpp, kernel relu_linear_attention of epona/cpu/conv.hpp)
// against the defining sums in float64 (S(m,n) = Σ_j relu(k)[j,m] relu(q)[j,n], out = Σ_m v S /
// (Σ_m S + eps)): the linear and the quadratic evaluation order on the same data, the
// reference's automatic choice (H·W > d linear), q/k/v interleaved per head, all-zero keys
// (out = 0, no NaN), and the whole module (qkv conv, attention, proj conv, RMSNorm2d).
// Tolerance rel <= 1e-5 (float32 sums over up to a few hundred positions).
#include <doctest/doctest.h>

#include "dcae_reference.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/nn/blocks/lite_mla.hpp"

using namespace epona;
using dcae_ref::HostTensor;
using dcae_ref::i64;

namespace {
HostTensor run_kernel(const HostTensor& qkv, i64 heads, i64 d, cpu::AttentionOrder order) {
  cpu::Context ctx;
  HostTensor work = qkv.clone();  // the kernel applies ReLU to q and k in place
  const i64 N = qkv.size(0), HW = qkv.size(2) * qkv.size(3);
  HostTensor out({N, heads * d, qkv.size(2), qkv.size(3)});
  cpu::relu_linear_attention(ctx, work.data(), out.data(), N, heads, d, HW, 1e-15f, order);
  return out;
}
}  // namespace

TEST_CASE("linear and quadratic orders agree with the float64 sums (and with each other)") {
  using cpu::AttentionOrder;
  const i64 N = 2, heads = 3, d = 8;
  for (auto [H, W] : {std::pair<i64, i64>{4, 5}, {2, 3}, {1, 1}, {3, 11}}) {
    INFO("H·W = " << H * W << " (head dim " << d << ")");
    const HostTensor qkv = dcae_ref::random_tensor({N, 3 * heads * d, H, W}, 100 + H * W);
    const auto ref = dcae_ref::relu_linear_attention(dcae_ref::to_vec(qkv), N, heads, d, H * W, 1e-15);
    const HostTensor lin = run_kernel(qkv, heads, d, AttentionOrder::Linear);
    const HostTensor quad = run_kernel(qkv, heads, d, AttentionOrder::Quadratic);
    const HostTensor autom = run_kernel(qkv, heads, d, AttentionOrder::Auto);
    CHECK(dcae_ref::rel_max(lin, ref) <= 1e-5);
    CHECK(dcae_ref::rel_max(quad, ref) <= 1e-5);
    CHECK(dcae_ref::rel_max(lin, dcae_ref::to_vec(quad)) <= 1e-5);
    // The automatic choice is the reference's: linear exactly when H·W > d.
    const HostTensor& expected = H * W > d ? lin : quad;
    CHECK(dcae_ref::rel_max(autom, dcae_ref::to_vec(expected)) == 0);
  }
}

TEST_CASE("q, k, v are interleaved per head: a head only sees its own 3d channels") {
  const i64 heads = 2, d = 4, H = 3, W = 4;
  HostTensor qkv = dcae_ref::random_tensor({1, 3 * heads * d, H, W}, 7);
  const HostTensor before = run_kernel(qkv, heads, d, cpu::AttentionOrder::Auto);
  for (i64 c = 3 * d; c < 6 * d; ++c)  // scramble all of head 1's q, k and v
    for (i64 p = 0; p < H * W; ++p) qkv.data()[c * H * W + p] *= -3.f;
  const HostTensor after = run_kernel(qkv, heads, d, cpu::AttentionOrder::Auto);
  for (i64 i = 0; i < d * H * W; ++i) CHECK(after.data()[i] == before.data()[i]);  // head 0 unchanged
  bool head1_changed = false;
  for (i64 i = d * H * W; i < 2 * d * H * W; ++i) head1_changed |= after.data()[i] != before.data()[i];
  CHECK(head1_changed);
}

TEST_CASE("all-zero keys give zero output, not NaN (the 1e-15 stays in float32)") {
  for (auto order : {cpu::AttentionOrder::Linear, cpu::AttentionOrder::Quadratic}) {
    const i64 d = 4;
    HostTensor qkv = dcae_ref::random_tensor({1, 3 * d, 2, 3}, 9);
    for (i64 i = d * 6; i < 2 * d * 6; ++i) qkv.data()[i] = -std::abs(qkv.data()[i]);  // ReLU(k) = 0
    const HostTensor out = run_kernel(qkv, 1, d, order);
    for (i64 i = 0; i < out.numel(); ++i) CHECK(out.data()[i] == 0.f);
  }
}

TEST_CASE("LiteMLA module: qkv 1x1 conv, attention, proj 1x1 conv, RMSNorm2d") {
  cpu::Context ctx;
  const i64 C = 64, d = 32, heads = C / d;
  nn::LiteMLA<Cpu, float> mla(C, nn::Norm2dKind::Rms, d);
  mla.randomize(11);
  for (auto [H, W] : {std::pair<i64, i64>{5, 7}, {4, 8}}) {  // 35 > 32: linear; 32: quadratic
    INFO("H·W = " << H * W);
    const HostTensor x = dcae_ref::random_tensor({2, C, H, W}, 12);
    const auto qkv = dcae_ref::conv2d(dcae_ref::to_vec(x), 2, C, H, W, dcae_ref::to_vec(mla.qkv.weight), nullptr, 3 * C,
                                      1, 1);
    const auto att = dcae_ref::relu_linear_attention(qkv, 2, heads, d, H * W, 1e-15);
    const auto proj = dcae_ref::conv2d(att, 2, C, H, W, dcae_ref::to_vec(mla.proj_conv.weight), nullptr, C, 1, 1);
    const auto ref = dcae_ref::rms_norm_2d(proj, 2, C, H * W, dcae_ref::to_vec(mla.proj_norm.weight),
                                           dcae_ref::to_vec(mla.proj_norm.bias), 1e-5);
    CHECK(dcae_ref::rel_max(mla.forward(ctx, x), ref) <= 1e-5);
  }
  using Mla = nn::LiteMLA<Cpu, float>;
  CHECK_THROWS_WITH_AS(Mla(40, nn::Norm2dKind::Rms, 32), doctest::Contains("32-wide heads"), Error);
}
