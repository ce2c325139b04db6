// GPU kernels of the DC-AE (cuda/conv/conv.cuh, norm2d.cuh, lite_mla.cuh, pixel_shuffle.cuh) against
// the CPU kernels (cpu/conv.hpp, cpu/pixel_shuffle.hpp) on the same random data: the GPU works
// on channels-last maps, the CPU on NCHW; results are compared after the layout change. Every
// GPU output is poisoned (NaN) first. float32: rel_l2 and max error <= 1e-5 (of max|ref|).
// bf16 (inputs and weights rounded to bf16 for both sides): bounds per rounding the kernel makes,
// u = 2^-8 each, stated at each check.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <vector>

#include "dcae_testing.cuh"
#include "epona/cpu/conv.hpp"
#include "epona/cpu/pixel_shuffle.hpp"
#include "epona/nn/conv2d.hpp"

using namespace epona;
using namespace epona::test;
using i64 = std::int64_t;

namespace {


std::uint32_t next_seed() {
  static std::uint32_t s = 1000;
  return ++s;
}

const char* act_name(ConvAct a) { return a == ConvAct::Relu ? "relu" : a == ConvAct::Silu ? "silu" : "none"; }

struct ConvCase {
  i64 N, C, H, W, O, k, groups;
};

// conv2d on both backends; bf16 bound: the conv output, the bias sum and the activation's
// result are each rounded once (activations have slope <= 1.1): max <= 3.5·u·M with M the
// largest pre-rounding value, rel_l2 <= 3u.
template <class T>
void check_conv(const ConvCase& c, ConvAct act, bool with_bias) {
  cuda::Context& ctx = gpu();
  HostF x = random_tensor({c.N, c.C, c.H, c.W}, next_seed());
  HostF w = random_tensor({c.O, c.C / c.groups, c.k, c.k}, next_seed(), -0.5f, 0.5f);
  HostF b = random_tensor({c.O}, next_seed());
  round_to<T>(x), round_to<T>(w), round_to<T>(b);
  const Conv2dShape s{c.N, c.C, c.H, c.W, c.O, c.k, c.groups};
  HostF ref({c.N, c.O, c.H, c.W}), pre({c.N, c.O, c.H, c.W});
  cpu::conv2d(host(), x.data(), w.data(), with_bias ? b.data() : nullptr, ref.data(), s, act);
  cpu::conv2d(host(), x.data(), w.data(), with_bias ? b.data() : nullptr, pre.data(), s, ConvAct::None);

  const Dev<T> dx = upload_map<T>(ctx, x);
  const Dev<T> dw = upload<T>(ctx, nn::conv_weight_layout<Cuda>(w));
  const Dev<T> db = upload<T>(ctx, b);
  Dev<T> dy({c.N, c.H, c.W, c.O});
  poison(ctx, dy);
  cuda::conv2d(ctx, dx.data(), dw.data(), with_bias ? db.data() : nullptr, dy.data(), s, act);
  const HostF out = download_map(ctx, dy);

  const double M = std::max(max_abs(pre), max_abs(ref));
  const Bound bound = std::is_same_v<T, float> ? one_rounding<T>(max_abs(ref)) : Bound{3 * kBf16Roundoff, 3.5 * kBf16Roundoff * M + kF32Tol * M};
  char what[160];
  std::snprintf(what, sizeof what, "conv2d %s %s N%lld C%lld %lldx%lld O%lld k%lld g%lld %s%s", type_name<T>(),
                engine_name(ctx.policy().conv_engine), (long long)c.N, (long long)c.C, (long long)c.H, (long long)c.W,
                (long long)c.O, (long long)c.k, (long long)c.groups, act_name(act), with_bias ? "+bias" : "");
  check_error(measure(out, ref), bound, what);
}

const std::vector<ConvCase>& conv_cases() {
  static const std::vector<ConvCase> cases = {
      {1, 5, 6, 11, 7, 3, 1},     // odd widths everywhere
      {2, 16, 9, 13, 24, 3, 1},   // batch 2, aligned channels
      {1, 64, 24, 40, 64, 3, 1},  // a ResBlock conv
      {1, 3, 32, 64, 32, 3, 1},   // encoder project_in: 3 input channels
      {1, 128, 16, 32, 12, 3, 1}, // decoder project_out: 12 outputs
      {1, 13, 7, 9, 3, 1, 1},     // 1x1, odd
      {1, 64, 8, 16, 192, 1, 1},  // 1x1 like LiteMLA's qkv
      {1, 3, 9, 17, 4, 5, 1},     // 5x5
      {2, 4, 5, 7, 6, 3, 2},      // 2 groups
      {1, 4, 3, 3, 8, 1, 4},      // grouped 1x1
      {1, 48, 5, 7, 48, 3, 48},   // depthwise, packed channels
      {2, 33, 9, 19, 33, 3, 33},  // depthwise, odd channels
      {1, 6, 5, 5, 6, 5, 6},      // depthwise 5x5
  };
  return cases;
}

}  // namespace

TEST_CASE("cuda conv2d (channels-last) vs cpu::conv2d: every geometry, both engines, f32 and bf16") {
  EPONA_REQUIRE_GPU();
  const std::string why = cuda::cudnn_unavailable(gpu());
  std::printf("cuDNN engine: %s\n", why.empty() ? "available" : why.c_str());
  for (const auto engine : {cuda::ConvEngine::Gemm, cuda::ConvEngine::Auto}) {
    UseEngine use(engine);
    for (const ConvCase& c : conv_cases()) {
      check_conv<float>(c, ConvAct::None, true);
      check_conv<bf16>(c, ConvAct::None, true);
    }
    check_conv<float>(conv_cases()[1], ConvAct::Relu, true);
    check_conv<float>(conv_cases()[1], ConvAct::Silu, false);
    check_conv<bf16>(conv_cases()[2], ConvAct::Silu, true);
    check_conv<bf16>(conv_cases()[2], ConvAct::Relu, false);
    check_conv<float>(conv_cases()[6], ConvAct::Silu, true);
    check_conv<bf16>(conv_cases()[10], ConvAct::Silu, true);
  }
}

TEST_CASE("cuda conv2d: cuDNN runs the model's aligned geometries when it is available") {
  EPONA_REQUIRE_GPU();
  if (!cuda::cudnn_unavailable(gpu()).empty()) {
    MESSAGE("cuDNN unavailable here: " << cuda::cudnn_unavailable(gpu()));
    return;
  }
  UseEngine use(cuda::ConvEngine::Cudnn);
  cuda::reset_conv_counts();
  check_conv<bf16>({1, 128, 32, 64, 128, 3, 1}, ConvAct::Relu, true);
  check_conv<float>({1, 128, 32, 64, 128, 3, 1}, ConvAct::None, true);
  check_conv<bf16>({1, 256, 16, 32, 1024, 3, 1}, ConvAct::None, true);
  CHECK(cuda::conv_counts().cudnn == 3);
  CHECK(cuda::conv_counts().gemm == 0);
  std::printf("  fused epilogues: %lld of 3 (refused: %s)\n", (long long)cuda::conv_counts().fused,
              cuda::conv_fusion_report().empty() ? "nowhere" : cuda::conv_fusion_report().c_str());
}

TEST_CASE("cuda conv2d Auto bf16: the measured engine choice gives the same results as either engine") {
  EPONA_REQUIRE_GPU();
  UseEngine use(cuda::ConvEngine::Auto);
  for (const bool tune : {true, false}) {
    ScopedPolicy tuning(gpu().policy().conv_tuning, tune);
    // the decoder's upsampling shapes, scaled down (many output channels on a small map), twice:
    // the first call times both engines, the second runs the remembered one
    for (int call = 0; call < 2; ++call) {
      check_conv<bf16>({1, 256, 8, 16, 1024, 3, 1}, ConvAct::None, true);
      check_conv<bf16>({1, 128, 4, 8, 512, 3, 1}, ConvAct::Relu, true);
    }
  }
  std::printf("  sent to the GEMM engine: %s\n",
              cuda::conv_tuning_report().empty() ? "none" : cuda::conv_tuning_report().c_str());
}

// residual += conv(x) + bias (conv2d_residual) vs the CPU conv plus the residual in float. bf16:
// the fused form rounds once, the unfused one rounds conv, conv + bias and the sum: max <= 3.5·u·M
// with M the largest of |conv + bias|, |residual| and |result|; rel_l2 <= 3u.
template <class T>
void check_conv_residual(const ConvCase& c, bool with_bias) {
  cuda::Context& ctx = gpu();
  HostF x = random_tensor({c.N, c.C, c.H, c.W}, next_seed());
  HostF w = random_tensor({c.O, c.C / c.groups, c.k, c.k}, next_seed(), -0.5f, 0.5f);
  HostF b = random_tensor({c.O}, next_seed());
  HostF r = random_tensor({c.N, c.O, c.H, c.W}, next_seed(), -4.f, 4.f);
  round_to<T>(x), round_to<T>(w), round_to<T>(b), round_to<T>(r);
  const Conv2dShape s{c.N, c.C, c.H, c.W, c.O, c.k, c.groups};
  HostF pre({c.N, c.O, c.H, c.W});
  cpu::conv2d(host(), x.data(), w.data(), with_bias ? b.data() : nullptr, pre.data(), s, ConvAct::None);
  HostF ref = pre.clone();
  for (i64 i = 0; i < ref.numel(); ++i) ref.data()[i] += r.data()[i];

  const Dev<T> dx = upload_map<T>(ctx, x);
  const Dev<T> dw = upload<T>(ctx, nn::conv_weight_layout<Cuda>(w));
  const Dev<T> db = upload<T>(ctx, b);
  Dev<T> dr = upload_map<T>(ctx, r);
  cuda::conv2d_residual(ctx, dx.data(), dw.data(), with_bias ? db.data() : nullptr, dr.data(), s);
  const HostF out = download_map(ctx, dr);

  const double M = std::max({max_abs(pre), max_abs(ref), max_abs(r)});
  const Bound bound = std::is_same_v<T, float> ? Bound{kF32Tol, kF32Tol * M}
                                               : Bound{3 * kBf16Roundoff, 3.5 * kBf16Roundoff * M + kF32Tol * M};
  char what[160];
  std::snprintf(what, sizeof what, "conv2d_residual %s %s%s N%lld C%lld %lldx%lld O%lld k%lld g%lld%s", type_name<T>(),
                engine_name(ctx.policy().conv_engine), ctx.policy().conv_fusion ? "" : " unfused", (long long)c.N,
                (long long)c.C, (long long)c.H, (long long)c.W, (long long)c.O, (long long)c.k, (long long)c.groups,
                with_bias ? " +bias" : "");
  check_error(measure(out, ref), bound, what);
}

TEST_CASE("cuda conv2d_residual (residual += conv + bias) vs the CPU: engines, fused and unfused") {
  EPONA_REQUIRE_GPU();
  const bool cudnn = cuda::cudnn_unavailable(gpu()).empty();
  std::vector<cuda::ConvEngine> engines{cuda::ConvEngine::Gemm, cuda::ConvEngine::Auto};
  if (cudnn) engines.push_back(cuda::ConvEngine::Cudnn);
  const std::vector<ConvCase> cases = {
      {2, 16, 9, 13, 16, 3, 1},   // batch 2, aligned
      {1, 64, 24, 40, 64, 3, 1},  // a ResBlock conv
      {1, 256, 16, 32, 256, 3, 1},  // stage-1 width
      {1, 5, 6, 11, 7, 3, 1},     // odd widths (unpacked tail)
      {1, 48, 5, 7, 48, 3, 48},   // depthwise: conv then the add pass
  };
  for (const bool fused : {true, false}) {
    UseFusion fusion(fused);
    for (const auto engine : engines) {
      UseEngine use(engine);
      cuda::reset_conv_counts();
      for (const ConvCase& c : cases) {
        if (engine == cuda::ConvEngine::Cudnn && c.C % 8 != 0) continue;  // cuDNN's NHWC wants packs of 8
        check_conv_residual<float>(c, true);
        check_conv_residual<bf16>(c, true);
      }
      check_conv_residual<bf16>(cases[1], false);
      const auto n = cuda::conv_counts();
      std::printf("  engine %s fusion %d: cudnn %lld (fused %lld), gemm %lld, depthwise %lld\n", engine_name(engine),
                  int(fused), (long long)n.cudnn, (long long)n.fused, (long long)n.gemm, (long long)n.depthwise);
      if (!fused || engine == cuda::ConvEngine::Gemm) CHECK(n.fused == 0);
    }
  }
  const std::string refused = cuda::conv_fusion_report();
  std::printf("cuDNN fused form refused: %s\n", refused.empty() ? "nowhere" : refused.c_str());
}

// fold_batch_norm vs a float64 fold on the host: w·s and beta - mean·s with s = gamma/sqrt(var+eps),
// each rounded once to T (float32: within 1e-6 relative; bf16: within 2^-8 of each value).
template <class T>
void check_fold(i64 O, i64 per_out) {
  cuda::Context& ctx = gpu();
  HostF w = random_tensor({O, per_out}, next_seed());
  HostF gamma = random_tensor({O}, next_seed(), 0.5f, 1.5f), beta = random_tensor({O}, next_seed());
  HostF mean = random_tensor({O}, next_seed()), var = random_tensor({O}, next_seed(), 0.01f, 3.f);
  round_to<T>(w);
  const float eps = 1e-5f;
  HostF ref_w({O, per_out}), ref_b({O});
  for (i64 o = 0; o < O; ++o) {
    const double sc = double(gamma.data()[o]) / std::sqrt(double(var.data()[o]) + double(eps));
    for (i64 j = 0; j < per_out; ++j) ref_w.data()[o * per_out + j] = float(double(w.data()[o * per_out + j]) * sc);
    ref_b.data()[o] = float(double(beta.data()[o]) - double(mean.data()[o]) * sc);
  }
  const Dev<T> dw = upload<T>(ctx, w);
  const Dev<float> dg = upload<float>(ctx, gamma), dbeta = upload<float>(ctx, beta), dm = upload<float>(ctx, mean),
                   dv = upload<float>(ctx, var);
  Dev<T> fw, fb;
  REQUIRE(fold_batch_norm(dw, dg, dbeta, dm, dv, eps, fw, fb));
  REQUIRE(fw.shape() == dw.shape());
  REQUIRE(fb.numel() == O);
  const HostF out_w = download(ctx, fw), out_b = download(ctx, fb);
  const double tol = std::is_same_v<T, float> ? 1e-6 : kBf16Roundoff;
  for (const auto& [out, ref] : {std::pair{&out_w, &ref_w}, std::pair{&out_b, &ref_b}}) {
    double worst = 0;
    for (i64 i = 0; i < ref->numel(); ++i)
      worst = std::max(worst, std::abs(double(out->data()[i]) - ref->data()[i]) / std::max(1e-30, double(std::abs(ref->data()[i]))));
    std::printf("  fold_batch_norm %s O%lld x %lld: worst relative error %.2e (bound %.1e)\n", type_name<T>(),
                (long long)O, (long long)per_out, worst, tol);
    CHECK(worst <= tol);
  }
}

TEST_CASE("fold_batch_norm: BatchNorm folded into conv weights and bias; off with the fusion") {
  EPONA_REQUIRE_GPU();
  check_fold<float>(37, 9 * 13);
  check_fold<bf16>(64, 9 * 64);
  cuda::KernelPolicy unfused;
  unfused.conv_fusion = false;
  Dev<float> w({4, 9}), g({4}), b({4}), m({4}), v({4}), fw, fb;
  CHECK_FALSE(fold_batch_norm(w, g, b, m, v, 1e-5f, fw, fb, unfused));
  CHECK(fw.empty());
}

TEST_CASE("cuda conv2d: GEMM engine over several im2col panels") {
  EPONA_REQUIRE_GPU();
  UseEngine use(cuda::ConvEngine::Gemm);
  ScopedPolicy<std::int64_t> panel(gpu().policy().conv_panel_bytes, 64 * 9 * 4 * 100);  // 100 rows of a 64-channel 3x3 float32 panel
  check_conv<float>({2, 64, 19, 23, 32, 3, 1}, ConvAct::Relu, true);
  check_conv<bf16>({1, 64, 19, 23, 32, 3, 1}, ConvAct::None, true);
}

TEST_CASE("cuda conv2d refuses bad geometry and a forced cuDNN engine it cannot run") {
  EPONA_REQUIRE_GPU();
  cuda::Context& ctx = gpu();
  Dev<float> x({1, 4, 4, 6}), w({6, 3, 3, 3}), y({1, 4, 4, 6});
  CHECK_THROWS_WITH_AS(cuda::conv2d(ctx, x.data(), w.data(), static_cast<const float*>(nullptr), y.data(),
                                    Conv2dShape{1, 6, 4, 4, 6, 3, 4}),
                       doctest::Contains("groups=4 must divide"), Error);
  CHECK_THROWS_WITH_AS(cuda::conv2d(ctx, x.data(), w.data(), static_cast<const float*>(nullptr), y.data(),
                                    Conv2dShape{1, 6, 4, 4, 6, 2, 1}),
                       doctest::Contains("kernel size must be odd"), Error);
}

namespace {

// RMSNorm2d / BatchNorm2d / residual += norm(branch) on N x H x W pixels of C channels.
template <class T>
void check_norms(i64 N, i64 C, i64 H, i64 W) {
  cuda::Context& ctx = gpu();
  const i64 HW = H * W;
  HostF x = random_tensor({N, C, H, W}, next_seed(), -2.f, 2.f), res = random_tensor({N, C, H, W}, next_seed());
  HostF wt = random_tensor({C}, next_seed(), 0.5f, 1.5f), bs = random_tensor({C}, next_seed());
  HostF mean = random_tensor({C}, next_seed()), var = random_tensor({C}, next_seed(), 0.5f, 2.f);
  round_to<T>(x), round_to<T>(res);
  const Dev<float> dw = upload<float>(ctx, wt), db = upload<float>(ctx, bs), dm = upload<float>(ctx, mean),
                   dv = upload<float>(ctx, var);
  const Dev<T> dx = upload_map<T>(ctx, x);
  char what[120];
  for (const bool batch : {false, true}) {
    HostF ref({N, C, H, W});
    if (batch)
      cpu::batch_norm_2d(host(), x.data(), ref.data(), N, C, HW, wt.data(), bs.data(), mean.data(), var.data(), 1e-5f);
    else
      cpu::rms_norm_2d(host(), x.data(), ref.data(), N, C, HW, wt.data(), bs.data(), 1e-5f);
    Dev<T> dy({N, H, W, C});
    poison(ctx, dy);
    if (batch)
      cuda::batch_norm_2d(ctx, dx.data(), dy.data(), N, C, HW, dw.data(), db.data(), dm.data(), dv.data(), 1e-5f);
    else
      cuda::rms_norm_2d(ctx, dx.data(), dy.data(), N, C, HW, dw.data(), db.data(), 1e-5f);
    std::snprintf(what, sizeof what, "%s %s C%lld pixels %lld", batch ? "batch_norm_2d" : "rms_norm_2d", type_name<T>(),
                  (long long)C, (long long)(N * HW));
    check_error(measure(download_map(ctx, dy), ref), one_rounding<T>(max_abs(ref)), what);

    // residual += norm(x): the normalised value and the sum are each rounded (bf16: two roundings).
    HostF sum = res.clone();
    for (i64 i = 0; i < sum.numel(); ++i) sum.data()[i] += float(T(ref.data()[i]));
    Dev<T> dres = upload_map<T>(ctx, res);
    cuda::norm_2d_add(ctx, dx.data(), dres.data(), N * HW, C, dw.data(), db.data(), batch ? dm.data() : nullptr,
                      batch ? dv.data() : nullptr, 1e-5f);
    std::snprintf(what, sizeof what, "norm_2d_add (%s) %s C%lld", batch ? "batch" : "rms", type_name<T>(), (long long)C);
    const Bound b = std::is_same_v<T, float> ? one_rounding<T>(max_abs(sum))
                                             : Bound{2 * kBf16Roundoff, kBf16Roundoff * (max_abs(ref) + max_abs(sum))};
    check_error(measure(download_map(ctx, dres), sum), b, what);
  }
}

}  // namespace

TEST_CASE("cuda rms_norm_2d / batch_norm_2d / norm_2d_add vs the CPU norms") {
  EPONA_REQUIRE_GPU();
  for (const i64 C : {128, 1024, 37, 2048, 8}) {
    check_norms<float>(2, C, 5, 7);
    check_norms<bf16>(2, C, 5, 7);
  }
  check_norms<bf16>(1, 256, 64, 96);
}

TEST_CASE("cuda apply_conv_act and gated_act vs the CPU") {
  EPONA_REQUIRE_GPU();
  cuda::Context& ctx = gpu();
  for (const i64 n : {1001, 4096}) {
    for (const ConvAct act : {ConvAct::Relu, ConvAct::Silu}) {
      const HostF x = random_tensor({n}, next_seed(), -4.f, 4.f);
      HostF ref = x.clone();
      cpu::apply_conv_act(host(), ref.data(), n, act);
      Dev<float> dx = upload<float>(ctx, x);
      cuda::apply_conv_act(ctx, dx.data(), n, act);
      check_error(measure(download(ctx, dx), ref), one_rounding<float>(max_abs(ref)),
                  std::string("apply_conv_act f32 ") + act_name(act));
    }
  }
  // GLUMBConv channels-last: rows = pixels, value = channels [0, h), gate = [h, 2h) of rows 2h wide.
  for (const i64 h : {64, 21}) {
    for (const ConvAct act : {ConvAct::Silu, ConvAct::Relu}) {
      const i64 rows = 77;
      HostF mixed = random_tensor({rows, 2 * h}, next_seed(), -3.f, 3.f);
      for (const bool half : {false, true}) {
        if (half) round_to<bf16>(mixed);
        HostF ref({rows, h});
        cpu::gated_act(host(), mixed.data(), mixed.data() + h, ref.data(), rows, h, 2 * h, h, act);
        const auto run = [&](auto tag) {
          using T = decltype(tag);
          const Dev<T> dm = upload<T>(ctx, mixed);
          Dev<T> dout({rows, h});
          poison(ctx, dout);
          cuda::gated_act(ctx, dm.data(), dm.data() + h, dout.data(), rows, h, 2 * h, h, act);
          // bf16: act(gate) and the product are each rounded: max <= u·(1.13·max|v·gate| + max|ref|).
          const Bound b = std::is_same_v<T, float> ? one_rounding<T>(max_abs(ref))
                                                   : Bound{2 * kBf16Roundoff, kBf16Roundoff * 2.2 * max_abs(ref) + 1e-6};
          check_error(measure(download(ctx, dout), ref), b,
                      std::string("gated_act ") + type_name<T>() + " " + act_name(act) + " h" + std::to_string(h));
        };
        if (half) run(bf16{}); else run(float{});
      }
    }
  }
  // SwiGLU in place: out = gate.
  {
    const i64 rows = 40, h = 256;
    const HostF value = random_tensor({rows, h}, next_seed(), -2.f, 2.f), gate = random_tensor({rows, h}, next_seed(), -2.f, 2.f);
    HostF ref({rows, h});
    cpu::gated_act(host(), value.data(), gate.data(), ref.data(), rows, h, h, h, ConvAct::Silu);
    const Dev<float> dv = upload<float>(ctx, value);
    Dev<float> dg = upload<float>(ctx, gate);
    cuda::gated_act(ctx, dv.data(), dg.data(), dg.data(), rows, h, h, h, ConvAct::Silu);
    check_error(measure(download(ctx, dg), ref), one_rounding<float>(max_abs(ref)), "gated_act f32 in place (SwiGLU)");
  }
}

namespace {

template <class T>
void check_mla(i64 N, i64 heads, i64 d, i64 H, i64 W, cpu::AttentionOrder order) {
  cuda::Context& ctx = gpu();
  const i64 HW = H * W, C = heads * d;
  HostF qkv = random_tensor({N, 3 * C, H, W}, next_seed());
  round_to<T>(qkv);
  HostF cpu_qkv = qkv.clone(), ref({N, C, H, W});
  cpu::relu_linear_attention(host(), cpu_qkv.data(), ref.data(), N, heads, d, HW, 1e-15f, order);
  const Dev<T> dq = upload_map<T>(ctx, qkv);
  Dev<T> dout({N, H, W, C});
  poison(ctx, dout);
  cuda::relu_linear_attention(ctx, dq.data(), dout.data(), N, heads, d, HW, 1e-15f, order);
  const char* o = order == cpu::AttentionOrder::Linear ? "linear" : order == cpu::AttentionOrder::Quadratic ? "quadratic" : "auto";
  char what[120];
  std::snprintf(what, sizeof what, "relu_linear_attention %s %s N%lld heads %lld d%lld HW %lld", type_name<T>(), o,
                (long long)N, (long long)heads, (long long)d, (long long)HW);
  check_error(measure(download_map(ctx, dout), ref), one_rounding<T>(max_abs(ref)), what);
  CHECK(download_map(ctx, dq).data()[0] == qkv.data()[0]);  // qkv is left as it was
}

}  // namespace

TEST_CASE("cuda relu_linear_attention vs the CPU: both orders, auto choice, head dims, batches") {
  EPONA_REQUIRE_GPU();
  using O = cpu::AttentionOrder;
  for (const O order : {O::Auto, O::Linear, O::Quadratic}) {
    check_mla<float>(2, 3, 32, 5, 13, order);
    check_mla<bf16>(2, 3, 32, 5, 13, order);
    check_mla<float>(1, 2, 16, 2, 3, order);  // 6 pixels: auto takes the quadratic order
  }
  check_mla<float>(1, 16, 32, 64, 128, O::Auto);  // decoder stage 3's map: many chunks
  check_mla<bf16>(1, 16, 32, 64, 128, O::Auto);
  check_mla<bf16>(1, 32, 32, 16, 32, O::Auto);
  check_mla<float>(2, 3, 16, 9, 11, O::Linear);   // d = 16: 16-byte loads, half the 32-wide tiles
  check_mla<float>(1, 2, 12, 7, 9, O::Linear);    // d = 12: element-wise loads and stores
  check_mla<bf16>(1, 2, 12, 7, 9, O::Linear);
  check_mla<float>(1, 4, 32, 1, 67, O::Linear);   // a partial last tile (67 pixels)
  cuda::Context& ctx = gpu();
  Dev<float> q({1, 1, 1, 3 * 64}), o({1, 1, 1, 64});
  CHECK_THROWS_WITH_AS(cuda::relu_linear_attention(ctx, q.data(), o.data(), 1, 1, 64, 1, 1e-15f),
                       doctest::Contains("head dim 64"), Error);
}

namespace {

template <class T>
void check_shuffles(i64 N, i64 C, i64 H, i64 W, i64 r, i64 c_out_down, i64 c_out_up) {
  cuda::Context& ctx = gpu();
  HostF x = random_tensor({N, C, H, W}, next_seed());
  round_to<T>(x);
  const ShuffleShape s{N, C, H, W, r};
  const Dev<T> dx = upload_map<T>(ctx, x);
  for (const bool accumulate : {false, true}) {
    // down: (N, C, H, W) -> (N, c_out_down, H/r, W/r); sums of g values in float32, one rounding.
    HostF base = random_tensor({N, c_out_down, H / r, W / r}, next_seed());
    round_to<T>(base);
    HostF ref = base.clone();
    cpu::pixel_unshuffle_average(host(), x.data(), ref.data(), s, c_out_down, accumulate);
    Dev<T> dd = upload_map<T>(ctx, base);
    if (!accumulate) poison(ctx, dd);
    cuda::pixel_unshuffle_average(ctx, dx.data(), dd.data(), s, c_out_down, accumulate);
    check_error(measure(download_map(ctx, dd), ref), one_rounding<T>(max_abs(ref)),
                std::string("pixel_unshuffle_average ") + type_name<T>() + " C" + std::to_string(C) + "->" +
                    std::to_string(c_out_down) + " r" + std::to_string(r) + (accumulate ? " +=" : ""));
    // up: (N, C, H, W) -> (N, c_out_up, H·r, W·r)
    HostF base_up = random_tensor({N, c_out_up, H * r, W * r}, next_seed());
    round_to<T>(base_up);
    HostF ref_up = base_up.clone();
    cpu::pixel_shuffle_duplicate(host(), x.data(), ref_up.data(), s, c_out_up, accumulate);
    Dev<T> du = upload_map<T>(ctx, base_up);
    if (!accumulate) poison(ctx, du);
    cuda::pixel_shuffle_duplicate(ctx, dx.data(), du.data(), s, c_out_up, accumulate);
    const HostF got = download_map(ctx, du);
    if (!accumulate) {  // a pure permutation: bit-exact
      const Diff e = measure(got, ref_up);
      CHECK(e.nans == 0);
      CHECK(e.max_abs == 0);
    }
    check_error(measure(got, ref_up), one_rounding<T>(max_abs(ref_up)),
                std::string("pixel_shuffle_duplicate ") + type_name<T>() + " C" + std::to_string(C) + "->" +
                    std::to_string(c_out_up) + " r" + std::to_string(r) + (accumulate ? " +=" : ""));
  }
}

}  // namespace

TEST_CASE("cuda pixel (un)shuffle with averaging / duplicating shortcuts vs the CPU") {
  EPONA_REQUIRE_GPU();
  check_shuffles<float>(2, 8, 6, 10, 2, 32, 2);    // plain unshuffle; shuffle 8 -> 2 channels
  check_shuffles<float>(1, 16, 4, 6, 2, 8, 8);     // averaging 64 -> 8; duplicating 16 -> 8·4 = 32 (rep 2)
  check_shuffles<bf16>(1, 16, 4, 6, 2, 8, 8);
  check_shuffles<float>(1, 64, 3, 5, 1, 32, 128);  // r = 1: the encoder's project_out mean, decoder's project_in repeat
  check_shuffles<bf16>(1, 64, 3, 5, 1, 32, 128);
  check_shuffles<float>(1, 3, 8, 8, 2, 12, 3);     // odd channels
}

namespace {

// The upsampling pair in one pass: out = shuffle_2(main) + D(x; C_out, 2) with main (N, C_out·4,
// H, W) and x (N, C_x, H, W), against the CPU's shuffle then accumulating shortcut (float32:
// exact sums of two values, bf16 one rounding of that sum) and against the GPU's two passes
// (bit for bit: the same single rounding).
template <class T>
void check_upsample_pair(i64 N, i64 C_out, i64 C_x, i64 H, i64 W) {
  cuda::Context& ctx = gpu();
  HostF main = random_tensor({N, 4 * C_out, H, W}, next_seed()), x = random_tensor({N, C_x, H, W}, next_seed());
  round_to<T>(main), round_to<T>(x);
  HostF ref({N, C_out, 2 * H, 2 * W});
  cpu::pixel_shuffle_duplicate(host(), main.data(), ref.data(), ShuffleShape{N, 4 * C_out, H, W, 2}, C_out, false);
  cpu::pixel_shuffle_duplicate(host(), x.data(), ref.data(), ShuffleShape{N, C_x, H, W, 2}, C_out, true);
  const Dev<T> dmain = upload_map<T>(ctx, main), dx = upload_map<T>(ctx, x);
  Dev<T> fused({N, 2 * H, 2 * W, C_out}), two_pass({N, 2 * H, 2 * W, C_out});
  poison(ctx, fused), poison(ctx, two_pass);
  REQUIRE(cuda::pixel_shuffle_add_duplicate_fused(ctx, dmain.data(), dx.data(), fused.data(),
                                                  ShuffleShape{N, 4 * C_out, H, W, 2}, C_out, C_x));
  cuda::pixel_shuffle_duplicate(ctx, dmain.data(), two_pass.data(), ShuffleShape{N, 4 * C_out, H, W, 2}, C_out, false);
  cuda::pixel_shuffle_duplicate(ctx, dx.data(), two_pass.data(), ShuffleShape{N, C_x, H, W, 2}, C_out, true);
  const HostF got = download_map(ctx, fused);
  const std::string what = std::string("upsample pair fused ") + type_name<T>() + " C_out " + std::to_string(C_out) +
                           " C_x " + std::to_string(C_x);
  check_error(measure(got, ref), one_rounding<T>(max_abs(ref)), what + " vs CPU");
  const Diff e = measure(got, download_map(ctx, two_pass));
  CHECK(e.nans == 0);
  CHECK(e.max_abs == 0);
}

}  // namespace

TEST_CASE("cuda upsampling pair (pixel shuffle + duplicating shortcut) in one pass vs the CPU and two passes") {
  EPONA_REQUIRE_GPU();
  check_upsample_pair<float>(1, 16, 32, 5, 7);   // rep 2 (decoder stages 3, 1: C -> C/2)
  check_upsample_pair<bf16>(1, 16, 32, 5, 7);
  check_upsample_pair<float>(2, 24, 24, 3, 9);   // rep 4 (stages 4, 2: C -> C), batch 2
  check_upsample_pair<bf16>(2, 24, 24, 3, 9);
  check_upsample_pair<bf16>(1, 256, 512, 8, 16);  // stage 1's widths
  // geometries the fused kernel declines (the caller then runs the two passes)
  const Dev<float> a({1, 4, 4, 12}), b({1, 4, 4, 3});
  Dev<float> o({1, 8, 8, 3});
  CHECK_FALSE(cuda::pixel_shuffle_add_duplicate_fused(gpu(), a.data(), b.data(), o.data(), ShuffleShape{1, 12, 4, 4, 2}, 3, 3));
}

TEST_CASE("cuda pixel_shuffle_to_nchw_fused (the decoder's last shuffle into NCHW float32) is exact") {
  EPONA_REQUIRE_GPU();
  cuda::Context& ctx = gpu();
  for (const auto& [N, C, H, W, r] : std::vector<std::array<i64, 5>>{{1, 3, 4, 6, 2}, {2, 5, 3, 7, 2}, {1, 2, 2, 3, 3}}) {
    HostF x = random_tensor({N, C * r * r, H, W}, next_seed());
    round_to<bf16>(x);
    HostF ref({N, C, H * r, W * r});
    cpu::pixel_shuffle_duplicate(host(), x.data(), ref.data(), ShuffleShape{N, C * r * r, H, W, r}, C, false);
    const auto run = [&](auto tag) {
      using T = decltype(tag);
      const Dev<T> dx = upload_map<T>(ctx, x);
      Dev<float> out({N, C, H * r, W * r});
      poison(ctx, out);
      REQUIRE(cuda::pixel_shuffle_to_nchw_fused(ctx, dx.data(), out.data(), N, C, H, W, r));
      const Diff e = measure(download(ctx, out), ref);
      INFO("pixel_shuffle_to_nchw ", type_name<T>(), " C ", C, " r ", r);
      CHECK(e.nans == 0);
      CHECK(e.max_abs == 0);
    };
    run(float{});
    run(bf16{});
  }
}

TEST_CASE("cuda transpose_last2 with type conversion is exact (up to bf16 rounding)") {
  EPONA_REQUIRE_GPU();
  cuda::Context& ctx = gpu();
  for (const auto [N, A, B] : {std::array<i64, 3>{2, 3, 1000}, {1, 77, 45}, {3, 32, 512}}) {
    const HostF x = random_tensor({N, A, B}, next_seed());
    HostF ref({N, B, A});
    cpu::transpose_last2(host(), x.data(), ref.data(), N, A, B);
    const Dev<float> dx = upload<float>(ctx, x);
    Dev<float> dy({N, B, A});
    poison(ctx, dy);
    cuda::transpose_last2(ctx, dx.data(), dy.data(), N, A, B);
    const Diff e = measure(download(ctx, dy), ref);
    CHECK(e.nans == 0);
    CHECK(e.max_abs == 0);
    Dev<bf16> dh({N, B, A});
    poison(ctx, dh);
    cuda::transpose_last2(ctx, dx.data(), dh.data(), N, A, B);
    HostF rounded = ref.clone();
    round_to<bf16>(rounded);
    const Diff eh = measure(download(ctx, dh), rounded);
    CHECK(eh.nans == 0);
    CHECK(eh.max_abs == 0);
  }
}

TEST_CASE("cuDNN state released before exit (and made again on demand)") {
  EPONA_REQUIRE_GPU();
  cuda::release_cudnn();
  CHECK(cuda::cudnn_unavailable(gpu()) == cuda::cudnn_unavailable(gpu()));
  cuda::release_cudnn();
}
