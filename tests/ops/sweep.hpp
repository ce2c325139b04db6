// The cross-backend op sweep (in the manner of ggml's test-backend-ops): every op the layers call
// by ADL on a backend Context, on seeded random inputs of small, odd shapes, against the float64
// reference of tests/ops/reference.hpp. Templated on the backend tag B (epona::Cpu, epona::Cuda)
// and the weight type W (float, bf16); activations are BackendTraits<B>::Activation<W> (float32
// on the CPU whatever W, W on the GPU). Each program (sweep_cpu.cpp, sweep_cuda.cu) specialises
// ops_sweep::Device<B> (upload, poisoned outputs, download, map layout) and calls sweep<B, W>().
//
// Error rule: err = max_i |got_i − ref_i| / max_i |ref_i| (rel_max, tests/metrics.hpp: infinite
// when any output is NaN or infinite, so an unwritten, poisoned element always fails). Inputs are
// rounded to their storage type before the reference sees them, so the error is the op's own.
// Bounds (kPointwise, kReduction below) by activation type: float32 activations 1e-5 for
// pointwise ops and norms, 1e-4 for sums over a product dimension (GEMM, convolution, attention:
// accumulation order); bf16 activations, and GEMMs with bf16 weights (see run_op), 1e-2 for
// pointwise ops (one rounding to bf16 moves a value by at most 2^-9 of itself; the GPU kernels
// round some intermediates to bf16 as PyTorch does) and 2e-2 for GEMM, convolution and attention
// (bf16 products and probabilities before P·V).
//
// Ops on one backend only (the concepts below; the sweep runs each where it exists, prints
// "not on this backend" elsewhere, and each program static_asserts which exist on its backend):
//   CPU only:  softmax_rows, fill.
//   CUDA only: linear_accumulate, linear_group, add_gated_layer_norm_modulate reading x and
//              writing x_out, convert, layer_norm_rope_qk, qk_norm_rope (segments),
//              try_assemble_frame_tokens, attention_qk_layer_norm, norm_2d_add, rms_norm_rows,
//              conv2d_residual (the CPU's layers compose the separate ops instead). layer_norm_rope_qk, try_assemble_frame_tokens and
//              attention_qk_layer_norm may decline a shape (return false): counted, not failed.
//   Not in the sweep yet (covered by tests/cuda/*.cu against the CPU): linear_batched called
//   directly (linear_group reaches it with equal strides), the fused shuffles (CUDA only);
//   BatchNorm folding (cuda/conv/conv_fold.cuh) is a bind-time weight transform, not an op.
//
// To add an op: its float64 loop in reference.hpp, its shapes in the table below (every shape
// lives there), and a run_op block in sweep() that draws inputs with Case::in, calls the op and
// records the error per case (log.record).
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <random>
#include <sstream>
#include <string>
#include <type_traits>
#include <vector>

#include "../metrics.hpp"
#include "epona/core/backend_capabilities.hpp"
#include "epona/core/backend_traits.hpp"
#include "epona/core/dtype.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/core/shapes.hpp"
#include "names.hpp"
#include "reference.hpp"

namespace ops_sweep {

using ops_ref::i64;
using ops_ref::Vec;
using epona::bf16;
using epona::ConvAct;
using epona::Epilogue;

// ---- the shapes of every case, in one place ----
struct RowsN { i64 rows, n; };  // rows of width n
struct GemmShape { i64 M, N, K; };
struct HeadsShape { i64 rows, heads, head_dim, pad; };  // row stride heads·head_dim + pad, heads at offset pad
struct AttnShape { i64 seqs, heads, lq, lk, d; epona::Mask mask; bool additive; };
struct ConvShape { i64 N, C, H, W, O, k, groups; bool bias; ConvAct act; };
struct Map2d { i64 N, C, HW; };
struct ShuffleCase { i64 N, C, H, W, r, channels_out; };
struct QkShape { i64 rows_q, rows_k, heads, head_dim; };
struct FrameShape { i64 frames, image_rows, actions, entries, width, items; };  // entries: all items'
struct MlaShape { i64 N, heads, d, HW; };

inline const std::vector<i64> kLengths{1, 7, 16, 33, 257, 1000};  // elementwise ops
inline const std::vector<RowsN> kRows{{1, 7}, {3, 64}, {5, 129}, {2, 1000}, {4, 20}, {2, 4099}};  // row ops, norms
inline const std::vector<GemmShape> kGemms{{1, 7, 5}, {3, 33, 17}, {5, 16, 64}, {17, 31, 40}, {70, 9, 33}, {33, 128, 96}, {8, 300, 257}};
inline const std::vector<HeadsShape> kHeads{{3, 2, 8, 5}, {5, 3, 64, 0}, {2, 1, 128, 16}, {4, 2, 6, 3}};
inline const std::vector<AttnShape> kAttention{
    {1, 1, 5, 5, 8, epona::Mask::None, false},     {2, 3, 17, 17, 64, epona::Mask::Causal, false},
    {1, 2, 3, 11, 32, epona::Mask::None, false},   {1, 2, 9, 9, 128, epona::Mask::None, true},
    {1, 2, 7, 12, 24, epona::Mask::Causal, false}, {2, 1, 20, 33, 20, epona::Mask::None, true},
    {1, 2, 70, 130, 64, epona::Mask::None, false}, {1, 1, 65, 65, 128, epona::Mask::Causal, true}};
// The GPU's fused layer_norm_rope_qk takes only rows its warp-per-row LayerNorm would (at least
// 8 per multiprocessor: 1056 on an H200), hence the long shape; it declines the others.
inline const std::vector<QkShape> kQkNorms{{5, 7, 2, 64}, {3, 3, 4, 32}, {16, 16, 1, 128}, {9, 4, 3, 16},
                                           {1100, 1060, 2, 64}};
inline const std::vector<AttnShape> kQkNormAttention{{2, 4, 16, 16, 128, epona::Mask::None, false},
                                                     {1, 8, 9, 9, 128, epona::Mask::None, false}};
inline const std::vector<FrameShape> kFrames{{2, 5, 3, 2, 64, 1},  {3, 4, 2, 4, 128, 1}, {1, 7, 0, 0, 256, 1},
                                            {2, 3, 1, 2, 40, 1},  {2, 5, 3, 6, 64, 2},  {3, 4, 2, 12, 128, 3},
                                            {1, 7, 0, 0, 256, 4}};
inline const std::vector<ConvShape> kConvs{
    {1, 3, 5, 7, 4, 1, 1, true, ConvAct::None},  {2, 4, 6, 5, 6, 3, 1, false, ConvAct::Relu},
    {1, 8, 9, 9, 8, 3, 8, true, ConvAct::Silu},  {1, 6, 4, 7, 9, 3, 3, true, ConvAct::None},
    {1, 16, 10, 10, 16, 3, 1, true, ConvAct::Silu}, {1, 5, 3, 3, 3, 3, 1, false, ConvAct::Relu},
    {1, 12, 4, 4, 6, 1, 2, false, ConvAct::Silu}, {1, 32, 16, 16, 32, 3, 1, true, ConvAct::Relu},
    {2, 24, 7, 9, 48, 1, 1, true, ConvAct::None}};
inline const std::vector<MlaShape> kLiteMla{{1, 2, 8, 12}, {2, 1, 16, 9}, {1, 3, 32, 40}};
inline const std::vector<epona::AttentionOrder> kMlaOrders{epona::AttentionOrder::Auto, epona::AttentionOrder::Linear,
                                                           epona::AttentionOrder::Quadratic};
inline const std::vector<Map2d> kMaps{{1, 3, 10}, {2, 16, 7}, {1, 33, 5}};
inline const std::vector<ShuffleCase> kUnshuffles{{1, 3, 4, 6, 2, 12}, {2, 4, 6, 6, 2, 8}, {1, 2, 6, 3, 3, 6}};
inline const std::vector<ShuffleCase> kShuffles{{1, 12, 2, 3, 2, 3}, {1, 4, 3, 2, 2, 4}, {2, 8, 2, 2, 2, 4}};
inline const std::vector<Epilogue> kEpilogues{Epilogue::None, Epilogue::GeluErf, Epilogue::GeluTanh, Epilogue::Silu};
inline const std::vector<ConvAct> kConvActs{ConvAct::None, ConvAct::Relu, ConvAct::Silu};

// ---- bounds (see the header comment) ----
struct Tol { double f32, bf16; };
inline constexpr Tol kPointwise{1e-5, 1e-2};
inline constexpr Tol kReduction{1e-4, 2e-2};

// ---- the ops that exist on one backend only, as concepts (Ctx a backend context, A its
// activation type): the sweep runs each where it holds, and each program static_asserts which
// hold on its backend, so a misspelt signature cannot silently skip an op ----
template <class Ctx, class A>
concept HasLinearAccumulate = requires(Ctx& cx, const A* p, float* y) {
  linear_accumulate(cx, p, i64{}, p, y, i64{}, i64{}, i64{}, i64{});
};
// The GPU's fused kernels are the library's named capabilities (core/backend_capabilities.hpp:
// GroupedLinear, AddGatedNormFromInput, QkLayerNormRope, JointQkNormRope, FusedFrameTokens,
// ShortAttentionQkNorm, ItemRowNorms), so the sweep checks the very concepts the layers choose
// them by (ItemRowNorms is checked bit for bit against its one-item form in tests/cuda/pointwise.cu).
template <class Ctx, class A>
concept HasConvert = requires(Ctx& cx, const float* s, A* p) { convert(cx, s, p, i64{}); };
template <class Ctx, class A>
concept HasNorm2dAdd = requires(Ctx& cx, const A* p, A* q, const float* f) {
  norm_2d_add(cx, p, q, i64{}, i64{}, f, f, f, f, 0.f);
};
template <class Ctx, class A>
concept HasRmsNormRows = requires(Ctx& cx, const float* x, A* y, const float* f) {
  rms_norm_rows(cx, x, y, i64{}, i64{}, f, 0.f);
};
template <class Ctx, class A>
concept HasConv2dResidual = requires(Ctx& cx, const A* p, A* q, epona::Conv2dShape s) {
  conv2d_residual(cx, p, p, p, q, s);
};
template <class Ctx, class A>
concept HasSoftmaxRows = requires(Ctx& cx, A* p) { softmax_rows(cx, p, i64{}, i64{}); };
template <class Ctx, class A>
concept HasFill = requires(Ctx& cx, A* p) { fill(cx, p, 0.f, i64{}); };
// Every one-backend op on the GPU (the CPU has exactly the last two).
template <class Ctx, class A>
concept HasCudaOnlyOps = HasLinearAccumulate<Ctx, A> && epona::GroupedLinear<Ctx, A> &&
                         epona::AddGatedNormFromInput<Ctx, A> && epona::QkLayerNormRope<Ctx, A> &&
                         epona::JointQkNormRope<Ctx, A> && epona::FusedFrameTokens<Ctx, A> && epona::ShortAttentionQkNorm<Ctx, A> &&
                         epona::ItemRowNorms<Ctx, A> &&
                         HasConvert<Ctx, A> && HasNorm2dAdd<Ctx, A> && HasRmsNormRows<Ctx, A> &&
                         HasConv2dResidual<Ctx, A>;
template <class Ctx, class A>
concept HasCpuOnlyOps = HasSoftmaxRows<Ctx, A> && HasFill<Ctx, A>;

// What a backend program provides (specialised in sweep_cpu.cpp, sweep_cuda.cu):
//   static constexpr const char* name; static constexpr bool channels_last (the DC-AE's maps);
//   template <class T> static Tensor<T, B> upload(Context&, const std::vector<float>&);
//   template <class T> static Tensor<T, B> output(Context&, i64 n);  // filled with NaN
//   template <class T> static std::vector<float> download(Context&, const Tensor<T, B>&);
template <class B> struct Device;

template <class B> using Context = typename epona::BackendTraits<B>::Context;
template <class B, class T> using Buf = epona::Tensor<T, B>;

template <class T>
float stored(float v) {
  if constexpr (std::is_same_v<T, bf16>) return float(bf16(v));
  return v;
}

// One case: its inputs (drawn, rounded to their type, uploaded; the float64 copy kept for the
// reference), its outputs (poisoned) and the comparison.
template <class B>
struct Case {
  Context<B>& ctx;
  std::mt19937 rng;

  template <class T>
  Buf<B, T> in(i64 n, Vec& values, float lo = -1.f, float hi = 1.f) {
    std::uniform_real_distribution<float> u(lo, hi);
    std::vector<float> f(static_cast<std::size_t>(n));
    for (auto& v : f) v = stored<T>(u(rng));
    values.assign(f.begin(), f.end());
    return Device<B>::template upload<T>(ctx, f);
  }
  // The same values already drawn (a permuted layout, a table).
  template <class T>
  Buf<B, T> put(const Vec& values) {
    std::vector<float> f(values.begin(), values.end());
    for (auto& v : f) v = stored<T>(v);
    return Device<B>::template upload<T>(ctx, f);
  }
  // RoPE tables (rows, head_dim/2) of random angles, float32 on the backend; `angle` gets the
  // tables' own angles (atan2 of the stored cos, sin) for the reference.
  struct RopeTables {
    Buf<B, float> cos, sin;
    std::vector<Vec> angle;
  };
  RopeTables rope_tables(i64 rows, i64 head_dim) {
    Vec a;
    in<float>(rows * head_dim / 2, a, -3.f, 3.f);
    Vec cosv(a.size()), sinv(a.size());
    RopeTables t;
    t.angle.resize(static_cast<std::size_t>(rows));
    for (std::size_t i = 0; i < a.size(); ++i) {
      cosv[i] = float(std::cos(a[i]));
      sinv[i] = float(std::sin(a[i]));
      t.angle[i / (head_dim / 2)].push_back(std::atan2(sinv[i], cosv[i]));
    }
    t.cos = put<float>(cosv);
    t.sin = put<float>(sinv);
    return t;
  }
  template <class T>
  Buf<B, T> out(i64 n) {
    return Device<B>::template output<T>(ctx, n);
  }
  template <class T>
  std::vector<float> get(const Buf<B, T>& t) {
    return Device<B>::download(ctx, t);
  }
  template <class T>
  double error(const Buf<B, T>& t, const Vec& ref) {
    const auto got = get(t);
    REQUIRE(got.size() == ref.size());
    return epona::test::rel_max(got.data(), ref.data(), static_cast<i64>(got.size()));
  }
};

// NCHW <-> the backend's layout of the DC-AE's maps ((N, C, HW) or channels-last (N, HW, C)).
template <class B>
Vec to_layout(const Vec& nchw, i64 N, i64 C, i64 HW) {
  return Device<B>::channels_last ? ops_ref::transpose_last2(nchw, N, C, HW) : nchw;
}
template <class B>
Vec from_layout(const Vec& v, i64 N, i64 C, i64 HW) {
  return Device<B>::channels_last ? ops_ref::transpose_last2(v, N, HW, C) : v;
}

inline const char* label(Epilogue e) { return epona::test::epilogue_name(e); }
inline const char* label(ConvAct a) { return epona::test::conv_act_name(a); }
inline double act_ref(Epilogue e, double v) {
  switch (e) {
    case Epilogue::None: return v;
    case Epilogue::GeluErf: return ops_ref::gelu_erf(v);
    case Epilogue::GeluTanh: return ops_ref::gelu_tanh(v);
    case Epilogue::Silu: return ops_ref::silu(v);
  }
  return v;
}
inline double act_ref(ConvAct a, double v) {
  return a == ConvAct::Relu ? ops_ref::relu(v) : a == ConvAct::Silu ? ops_ref::silu(v) : v;
}

// Per op: cases run and the worst error; one CHECK per case naming op, shape and error.
struct OpLog {
  std::string op;
  double bound;
  int cases = 0, declined = 0;  // declined: an op that may refuse a shape (returns false) did
  double worst = 0;
  std::string worst_case;

  void record(const std::string& shape, double err) {
    ++cases;
    if (!(err <= worst) || cases == 1) worst = err, worst_case = shape;
    INFO(op, " ", shape, ": error ", err, " (bound ", bound, ")");
    CHECK(err <= bound);
  }
  void summary(const std::string& backend, const std::string& types) const {
    if (cases == 0 && declined == 0) {
      MESSAGE(backend, " ", types, " ", op, ": not on this backend");
      return;
    }
    MESSAGE(backend, " ", types, " ", op, ": ", cases, " cases, worst error ", worst, " at ", worst_case, " (bound ",
            bound, ")", declined ? ", shapes declined: " + std::to_string(declined) : std::string());
  }
};

template <class... V>
std::string shape(const V&... v) {
  std::ostringstream s;
  const char* sep = "";
  ((s << sep << v, sep = " "), ...);
  return s.str();
}

// Runs every case of one op: body(Case&, OpLog&) per case, each with its own seed.
// The bound is bf16's when the activations are bf16, or when `weights_round` (a product with
// bf16 weights: the CPU's AVX512-BF16 GEMM rounds the activations to bf16 too,
// docs/performance.md "The bf16-weight path").
template <class B, class W, class Body>
void run_op(Context<B>& ctx, const char* op, Tol tol, std::uint32_t seed, Body body, bool weights_round = false) {
  using A = typename epona::BackendTraits<B>::template Activation<W>;
  const bool bf16_bound = std::is_same_v<A, bf16> || (weights_round && std::is_same_v<W, bf16>);
  OpLog log{op, bf16_bound ? tol.bf16 : tol.f32, 0, 0, 0, {}};
  Case<B> c{ctx, std::mt19937(seed)};
  body(c, log);
  log.summary(Device<B>::name, std::is_same_v<W, bf16> ? "bf16" : "f32");
}

// ---- the ops ----
template <class B, class W>
void sweep(Context<B>& ctx) {
  using A = typename epona::BackendTraits<B>::template Activation<W>;
  using Ctx = Context<B>;
  const float eps = 1e-5f;

  // linear: y = act(x · wᵀ + b), every epilogue, with and without bias.
  run_op<B, W>(ctx, "linear", kReduction, 1, [&](Case<B>& c, OpLog& log) {
    for (const auto [M, N, K] : kGemms)
      for (const Epilogue e : kEpilogues)
        for (const bool with_bias : {false, true}) {
          Vec x, w, b;
          auto dx = c.template in<A>(M * K, x);
          auto dw = c.template in<W>(N * K, w, -0.5f, 0.5f);
          auto db = c.template in<W>(N, b);
          auto dy = c.template out<A>(M * N);
          linear(ctx, dx.data(), K, dw.data(), with_bias ? db.data() : nullptr, dy.data(), N, M, N, K, e);
          const Vec ref = ops_ref::map(ops_ref::linear(x, M, w, with_bias ? &b : nullptr, K, N),
                                       [e](double v) { return act_ref(e, v); });
          log.record(shape("M", M, "N", N, "K", K, label(e), with_bias ? "bias" : "no-bias"), c.error(dy, ref));
        }
  }, true);

  // linear_accumulate: y += x · wᵀ into a float32 y.
  run_op<B, W>(ctx, "linear_accumulate", kReduction, 2, [&](Case<B>& c, OpLog& log) {
    if constexpr (HasLinearAccumulate<Ctx, A>) {
      for (const auto [M, N, K] : kGemms) {
        Vec x, w, y0;
        auto dx = c.template in<A>(M * K, x);
        auto dw = c.template in<A>(N * K, w, -0.5f, 0.5f);
        auto dy = c.template in<float>(M * N, y0);
        linear_accumulate(ctx, dx.data(), K, dw.data(), dy.data(), N, M, N, K);
        log.record(shape("M", M, "N", N, "K", K), c.error(dy, ops_ref::add_gated(y0, ops_ref::linear(x, M, w, nullptr, K, N), nullptr, M, N)));
      }
    }
  });

  // linear_group: `count` products of one x (or of x blocks x_stride apart) into y blocks.
  run_op<B, W>(ctx, "linear_group", kReduction, 3, [&](Case<B>& c, OpLog& log) {
    if constexpr (epona::GroupedLinear<Ctx, A>) {
      for (const auto [M, N, K] : kGemms)
        for (const i64 x_stride : {i64{0}, M * K}) {
          const i64 count = 3;
          const Epilogue e = kEpilogues[(M + N) % kEpilogues.size()];
          Vec x;
          auto dx = c.template in<A>(x_stride ? count * M * K : M * K, x);
          std::vector<Vec> w(count), b(count);
          std::vector<Buf<B, A>> dw, db;
          std::vector<const A*> pw, pb;
          for (i64 g = 0; g < count; ++g) {
            dw.push_back(c.template in<A>(N * K, w[g], -0.5f, 0.5f));
            db.push_back(c.template in<A>(N, b[g]));
            pw.push_back(dw.back().data());
            pb.push_back(g == 1 ? nullptr : db.back().data());
          }
          auto dy = c.template out<A>(count * M * N);
          linear_group(ctx, dx.data(), K, x_stride, pw, pb, dy.data(), N, M * N, M, N, K, e);
          Vec ref;
          for (i64 g = 0; g < count; ++g) {
            const Vec xg(x.begin() + g * x_stride, x.begin() + g * x_stride + M * K);
            const Vec yg = ops_ref::map(ops_ref::linear(xg, M, w[g], g == 1 ? nullptr : &b[g], K, N),
                                        [e](double v) { return act_ref(e, v); });
            ref.insert(ref.end(), yg.begin(), yg.end());
          }
          log.record(shape("M", M, "N", N, "K", K, "x_stride", x_stride, label(e)), c.error(dy, ref));
        }
    }
  });

  // Activations: GELU erf, GELU tanh and SiLU in place, SiLU into another buffer. `op_run(x, y, n)`
  // runs the op and says whether its result is in y (else in x).
  const auto unary = [&](const char* op, std::uint32_t seed, auto op_run, double (*ref)(double)) {
    run_op<B, W>(ctx, op, kPointwise, seed, [&](Case<B>& c, OpLog& log) {
      for (const i64 n : kLengths) {
        Vec x;
        auto dx = c.template in<A>(n, x, -4.f, 4.f);
        auto dy = c.template out<A>(n);
        const bool into_y = op_run(dx.data(), dy.data(), n);
        log.record(shape("n", n), c.error(into_y ? dy : dx, ops_ref::map(x, ref)));
      }
    });
  };
  unary("gelu_erf", 4, [&](A* x, A*, i64 n) { return gelu_erf(ctx, x, n), false; }, ops_ref::gelu_erf);
  unary("gelu_tanh", 5, [&](A* x, A*, i64 n) { return gelu_tanh(ctx, x, n), false; }, ops_ref::gelu_tanh);
  unary("silu", 6, [&](A* x, A*, i64 n) { return silu(ctx, x, n), false; }, ops_ref::silu);
  unary("silu_to", 7, [&](A* x, A* y, i64 n) { return silu_to(ctx, x, y, n), true; }, ops_ref::silu);

  // Residual adds: x += y, x[r] += gate ⊙ y[r], x[r] += b.
  run_op<B, W>(ctx, "add_inplace", kPointwise, 8, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      Vec x, y;
      auto dx = c.template in<A>(rows * n, x);
      auto dy = c.template in<A>(rows * n, y);
      add_inplace(ctx, dx.data(), dy.data(), rows * n);
      log.record(shape("n", rows * n), c.error(dx, ops_ref::add_gated(x, y, nullptr, rows, n)));
    }
  });
  run_op<B, W>(ctx, "add_gated", kPointwise, 9, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      Vec x, y, g;
      auto dx = c.template in<A>(rows * n, x);
      auto dy = c.template in<A>(rows * n, y);
      auto dg = c.template in<A>(n, g);
      add_gated(ctx, dx.data(), dy.data(), dg.data(), rows, n);
      log.record(shape("rows", rows, "n", n), c.error(dx, ops_ref::add_gated(x, y, &g, rows, n)));
    }
  });
  run_op<B, W>(ctx, "add_row_broadcast", kPointwise, 10, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      Vec x, b;
      auto dx = c.template in<A>(rows * n, x);
      auto db = c.template in<A>(n, b);
      add_row_broadcast(ctx, dx.data(), db.data(), rows, n);
      Vec ref = x;
      for (i64 r = 0; r < rows; ++r)
        for (i64 i = 0; i < n; ++i) ref[r * n + i] += b[i];
      log.record(shape("rows", rows, "n", n), c.error(dx, ref));
    }
  });

  // LayerNorm: no affine, weight and bias, weight only; and the adaLN modulation.
  run_op<B, W>(ctx, "layer_norm", kPointwise, 11, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows)
      for (const int affine : {0, 1, 2}) {
        Vec x, w, b;
        auto dx = c.template in<A>(rows * n, x, -2.f, 4.f);
        auto dw = c.template in<float>(n, w, 0.5f, 1.5f);
        auto db = c.template in<float>(n, b);
        auto dy = c.template out<A>(rows * n);
        const float* pw = affine ? dw.data() : nullptr;
        const float* pb = affine == 1 ? db.data() : nullptr;
        layer_norm(ctx, dx.data(), dy.data(), rows, n, pw, pb, eps);
        const Vec ref = ops_ref::layer_norm(x, rows, n, eps, affine ? &w : nullptr, affine == 1 ? &b : nullptr);
        log.record(shape("rows", rows, "n", n, affine == 0 ? "plain" : affine == 1 ? "weight+bias" : "weight"),
                   c.error(dy, ref));
      }
  });
  run_op<B, W>(ctx, "layer_norm_modulate", kPointwise, 12, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      Vec x, sh, sc;
      auto dx = c.template in<A>(rows * n, x, -2.f, 4.f);
      auto dsh = c.template in<A>(n, sh);
      auto dsc = c.template in<A>(n, sc, -0.5f, 0.5f);
      auto dy = c.template out<A>(rows * n);
      layer_norm_modulate(ctx, dx.data(), dy.data(), rows, n, dsh.data(), dsc.data(), eps);
      log.record(shape("rows", rows, "n", n), c.error(dy, ops_ref::modulate(x, rows, n, eps, sh.data(), sc.data())));
    }
  });

  // Fused residual + norm: x += y; out = LN(x)·w + b, and x += gate ⊙ y; out = modulate(x).
  run_op<B, W>(ctx, "add_layer_norm", kPointwise, 13, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      Vec x, y, w, b;
      auto dx = c.template in<A>(rows * n, x);
      auto dy = c.template in<A>(rows * n, y);
      auto dw = c.template in<float>(n, w, 0.5f, 1.5f);
      auto db = c.template in<float>(n, b);
      auto dout = c.template out<A>(rows * n);
      add_layer_norm(ctx, dx.data(), dy.data(), dout.data(), rows, n, dw.data(), db.data(), eps);
      const Vec sum = ops_ref::add_gated(x, y, nullptr, rows, n);
      log.record(shape("rows", rows, "n", n, "x"), c.error(dx, sum));
      log.record(shape("rows", rows, "n", n, "out"), c.error(dout, ops_ref::layer_norm(sum, rows, n, eps, &w, &b)));
    }
  });
  // x += gate ⊙ y; out = modulate(x): in place, and (where it exists) reading x, writing x_out.
  const auto agln = [&](const char* op, std::uint32_t seed, bool separate) {
    run_op<B, W>(ctx, op, kPointwise, seed, [&](Case<B>& c, OpLog& log) {
      constexpr bool has_separate = epona::AddGatedNormFromInput<Ctx, A>;
      if (separate && !has_separate) return;
      for (const auto [rows, n] : kRows) {
        Vec x, y, g, sh, sc;
        auto dx = c.template in<A>(rows * n, x);
        auto dy = c.template in<A>(rows * n, y);
        auto dg = c.template in<A>(n, g);
        auto dsh = c.template in<A>(n, sh);
        auto dsc = c.template in<A>(n, sc, -0.5f, 0.5f);
        auto dxo = c.template out<A>(rows * n);
        auto dout = c.template out<A>(rows * n);
        if constexpr (has_separate)
          if (separate)
            add_gated_layer_norm_modulate(ctx, static_cast<const A*>(dx.data()), dxo.data(), dy.data(), dg.data(),
                                          dout.data(), rows, n, dsh.data(), dsc.data(), eps);
        if (!separate)
          add_gated_layer_norm_modulate(ctx, dx.data(), dy.data(), dg.data(), dout.data(), rows, n, dsh.data(),
                                        dsc.data(), eps);
        const Vec sum = ops_ref::add_gated(x, y, &g, rows, n);
        if (separate) log.record(shape("rows", rows, "n", n, "x untouched"), c.error(dx, x));
        log.record(shape("rows", rows, "n", n, separate ? "x_out" : "x"), c.error(separate ? dxo : dx, sum));
        log.record(shape("rows", rows, "n", n, "out"),
                   c.error(dout, ops_ref::modulate(sum, rows, n, eps, sh.data(), sc.data())));
      }
    });
  };
  agln("add_gated_layer_norm_modulate", 14, false);
  agln("add_gated_layer_norm_modulate (x, x_out)", 15, true);

  // Per-head RMSNorm, RoPE and the two composed, in place on heads `pad` floats into rows of
  // stride heads·head_dim + pad (the channels outside the heads must stay as they were).
  const auto heads_op = [&](const char* op, std::uint32_t seed, bool norm, bool rotate) {
    run_op<B, W>(ctx, op, kPointwise, seed, [&](Case<B>& c, OpLog& log) {
      for (const auto [rows, heads, hd, pad] : kHeads) {
        const i64 stride = heads * hd + pad;
        Vec x, scale;
        auto dx = c.template in<A>(rows * stride, x, -2.f, 2.f);
        auto dscale = c.template in<float>(hd, scale, 0.5f, 1.5f);
        const auto t = c.rope_tables(rows, hd);
        A* p = dx.data() + pad;
        if (norm && rotate)
          rms_norm_rope_heads(ctx, p, rows, stride, heads, hd, dscale.data(), eps, t.cos.data(), t.sin.data());
        else if (norm)
          rms_norm_heads(ctx, p, rows, stride, heads, hd, dscale.data(), eps);
        else
          apply_rope(ctx, p, rows, stride, heads, hd, t.cos.data(), t.sin.data());
        Vec ref = x;
        if (norm) ops_ref::rms_heads(ref, rows, stride, pad, heads, hd, scale, eps);
        if (rotate) ops_ref::rope(ref, rows, stride, pad, heads, hd, t.angle);
        log.record(shape("rows", rows, "heads", heads, "head_dim", hd, "pad", pad), c.error(dx, ref));
      }
    });
  };
  heads_op("rms_norm_heads", 16, true, false);
  heads_op("apply_rope", 17, false, true);
  heads_op("rms_norm_rope_heads", 18, true, true);

  // q = LN_q(q), k = LN_k(k) (affine, over the whole row) then RoPE on both, in place; the op may
  // decline a width (returns false): such shapes are counted, not failed.
  run_op<B, W>(ctx, "layer_norm_rope_qk", kPointwise, 34, [&](Case<B>& c, OpLog& log) {
    if constexpr (epona::QkLayerNormRope<Ctx, A>) {
      for (const auto [rows_q, rows_k, heads, hd] : kQkNorms) {
        const i64 n = heads * hd;
        Vec q, k, qw, qb, kw, kb;
        auto dq = c.template in<A>(rows_q * n, q, -2.f, 3.f);
        auto dk = c.template in<A>(rows_k * n, k, -2.f, 3.f);
        auto dqw = c.template in<float>(n, qw, 0.5f, 1.5f);
        auto dqb = c.template in<float>(n, qb);
        auto dkw = c.template in<float>(n, kw, 0.5f, 1.5f);
        auto dkb = c.template in<float>(n, kb);
        const auto t = c.rope_tables(std::max(rows_q, rows_k), hd);
        if (!layer_norm_rope_qk(ctx, dq.data(), rows_q, dk.data(), rows_k, n, dqw.data(), dqb.data(), eps, dkw.data(),
                                dkb.data(), 1e-6f, hd, t.cos.data(), t.sin.data())) {
          ++log.declined;
          continue;
        }
        Vec rq = ops_ref::layer_norm(q, rows_q, n, eps, &qw, &qb), rk = ops_ref::layer_norm(k, rows_k, n, 1e-6, &kw, &kb);
        ops_ref::rope(rq, rows_q, n, 0, heads, hd, t.angle);
        ops_ref::rope(rk, rows_k, n, 0, heads, hd, t.angle);
        log.record(shape("rows_q", rows_q, "rows_k", rows_k, "heads", heads, "head_dim", hd, "q"), c.error(dq, rq));
        log.record(shape("rows_q", rows_q, "rows_k", rows_k, "heads", heads, "head_dim", hd, "k"), c.error(dk, rk));
      }
    }
  });

  // The joint QK RMSNorm + RoPE over segments of a packed qkv buffer: keys of rows [first, end),
  // queries of rows [q_first, end), each with its segment's scales; other rows stay as they were.
  run_op<B, W>(ctx, "qk_norm_rope (segments)", kPointwise, 35, [&](Case<B>& c, OpLog& log) {
    if constexpr (epona::JointQkNormRope<Ctx, A>) {
      for (const auto [rows_q, rows_k, heads, hd] : kQkNorms) {
        const i64 rows = rows_q + rows_k, hw = heads * hd, stride = 3 * hw;
        Vec x, qs0, ks0, qs1, ks1;
        auto dx = c.template in<A>(rows * stride, x, -2.f, 2.f);
        auto dqs0 = c.template in<float>(hd, qs0, 0.5f, 1.5f);
        auto dks0 = c.template in<float>(hd, ks0, 0.5f, 1.5f);
        auto dqs1 = c.template in<float>(hd, qs1, 0.5f, 1.5f);
        auto dks1 = c.template in<float>(hd, ks1, 0.5f, 1.5f);
        const auto t = c.rope_tables(rows, hd);
        // Segment 0: rows [0, rows_q), queries from row 1 (row 0's queries untouched); segment 1
        // the rest.
        using Segment = epona::QkNormRopeSegment;
        const std::array<Segment, 2> segs{Segment{0, std::min<i64>(1, rows_q), rows_q, dqs0.data(), dks0.data()},
                                          Segment{rows_q, rows_q, rows, dqs1.data(), dks1.data()}};
        qk_norm_rope(ctx, dx.data(), stride, hw, heads, hd, eps, t.cos.data(), t.sin.data(), segs);
        Vec ref = x;
        // The reference on rows [a, b) at column offset `off`: per head RMSNorm, then RoPE.
        const auto norm_rope_rows = [&](i64 a, i64 b, i64 off, const Vec& scale) {
          Vec part(ref.begin() + a * stride, ref.begin() + b * stride);
          ops_ref::rms_heads(part, b - a, stride, off, heads, hd, scale, eps);
          const std::vector<Vec> angle(t.angle.begin() + a, t.angle.begin() + b);
          ops_ref::rope(part, b - a, stride, off, heads, hd, angle);
          std::copy(part.begin(), part.end(), ref.begin() + a * stride);
        };
        norm_rope_rows(0, rows_q, hw, ks0);
        norm_rope_rows(std::min<i64>(1, rows_q), rows_q, 0, qs0);
        norm_rope_rows(rows_q, rows, hw, ks1);
        norm_rope_rows(rows_q, rows, 0, qs1);
        log.record(shape("rows", rows_q, "+", rows_k, "heads", heads, "head_dim", hd), c.error(dx, ref));
      }
    }
  });

  // The MST's frame tokens (FrameTokens): LN of the image rows + time embedding, action rows +
  // time embedding, into float32 tokens; the op may decline (returns false).
  run_op<B, W>(ctx, "try_assemble_frame_tokens", kPointwise, 36, [&](Case<B>& c, OpLog& log) {
    if constexpr (epona::FusedFrameTokens<Ctx, A>) {
      for (const auto [frames, image_rows, actions, entries, width, items] : kFrames) {
        const epona::FrameTokens ft{frames, image_rows, actions, entries, width, eps, items};
        Vec img, act, te, w, b;
        auto dimg = c.template in<A>(items * frames * image_rows * width, img, -2.f, 3.f);
        auto dact = c.template in<float>(std::max<i64>(1, actions * entries * width), act);
        auto dte = c.template in<float>(frames * width, te);
        auto dw = c.template in<float>(width, w, 0.5f, 1.5f);
        auto db = c.template in<float>(width, b);
        auto dout = c.template out<float>(items * frames * ft.tokens() * width);
        if (!try_assemble_frame_tokens(ctx, dimg.data(), dact.data(), dte.data(), dw.data(), db.data(), dout.data(), ft)) {
          ++log.declined;
          continue;
        }
        log.record(shape("frames", frames, "image_rows", image_rows, "actions", actions, "entries", entries, "width", width,
                         "items", items),
                   c.error(dout, ops_ref::frame_tokens(img, act, te, w, b, frames, image_rows, actions, entries, width, eps,
                                                        items)));
      }
    }
  });

  // Attention over LN_q(q), LN_k(k) (each over a token's heads·head_dim channels, affine) in one
  // kernel; q, k only read; it declines what it does not fit (float32, long sequences, ...).
  run_op<B, W>(ctx, "attention_qk_layer_norm", kReduction, 37, [&](Case<B>& c, OpLog& log) {
    if constexpr (epona::ShortAttentionQkNorm<Ctx, A>) {
      for (const auto [seqs, heads, lq, lk, d, mask, additive] : kQkNormAttention) {
        const i64 hd = heads * d, kv_row = 2 * hd;
        Vec q, kv, qw, qb, kw, kb;
        auto dq = c.template in<A>(seqs * lq * hd, q, -2.f, 2.f);
        auto dkv = c.template in<A>(seqs * lk * kv_row, kv, -2.f, 2.f);
        auto dqw = c.template in<float>(hd, qw, 0.5f, 1.5f);
        auto dqb = c.template in<float>(hd, qb);
        auto dkw = c.template in<float>(hd, kw, 0.5f, 1.5f);
        auto dkb = c.template in<float>(hd, kb);
        auto dout = c.template out<A>(seqs * lq * hd);
        epona::AttentionShape a;
        a.seqs = seqs, a.heads = heads, a.lq = lq, a.lk = lk, a.head_dim = d, a.mask = mask;
        a.q_seq = lq * hd, a.q_row = hd, a.k_seq = a.v_seq = lk * kv_row, a.k_row = a.v_row = kv_row;
        a.o_seq = lq * hd, a.o_row = hd;
        if (!attention_qk_layer_norm(ctx, static_cast<const A*>(dq.data()), dkv.data(), dkv.data() + hd, dout.data(), a,
                                     dqw.data(), dqb.data(), eps, dkw.data(), dkb.data(), 1e-6f)) {
          ++log.declined;
          continue;
        }
        Vec k, v;
        for (i64 r = 0; r < seqs * lk; ++r) {
          k.insert(k.end(), kv.begin() + r * kv_row, kv.begin() + r * kv_row + hd);
          v.insert(v.end(), kv.begin() + r * kv_row + hd, kv.begin() + (r + 1) * kv_row);
        }
        const Vec qn = ops_ref::layer_norm(q, seqs * lq, hd, eps, &qw, &qb);
        const Vec kn = ops_ref::layer_norm(k, seqs * lk, hd, 1e-6, &kw, &kb);
        const Vec ref = ops_ref::attention(qn, {lq * hd, hd}, kn, {lk * hd, hd}, v, {lk * hd, hd}, seqs, heads, lq, lk, d,
                                           false);
        log.record(shape("seqs", seqs, "heads", heads, "lq", lq, "lk", lk, "d", d), c.error(dout, ref));
      }
    }
  });

  // Attention over strided q (rows padded by 8) and packed k|v rows; o dense.
  run_op<B, W>(ctx, "attention", kReduction, 19, [&](Case<B>& c, OpLog& log) {
    for (const auto [seqs, heads, lq, lk, d, mask, additive] : kAttention) {
      const i64 hd = heads * d, q_row = hd + 8, kv_row = 2 * hd;
      Vec q, kv, m;
      auto dq = c.template in<A>(seqs * lq * q_row, q, -2.f, 2.f);
      auto dkv = c.template in<A>(seqs * lk * kv_row, kv, -2.f, 2.f);
      auto dm = c.template in<float>(lq * lk, m, -2.f, 0.f);
      auto dout = c.template out<A>(seqs * lq * hd);
      epona::AttentionShape a;
      a.seqs = seqs, a.heads = heads, a.lq = lq, a.lk = lk, a.head_dim = d;
      a.q_seq = lq * q_row, a.q_row = q_row, a.k_seq = a.v_seq = lk * kv_row, a.k_row = a.v_row = kv_row;
      a.o_seq = lq * hd, a.o_row = hd, a.mask = mask, a.additive_mask = additive ? dm.data() : nullptr;
      attention(ctx, dq.data(), dkv.data(), dkv.data() + hd, dout.data(), a);
      const Vec v(kv.begin() + hd, kv.end());
      const Vec ref = ops_ref::attention(q, {lq * q_row, q_row}, kv, {lk * kv_row, kv_row}, v, {lk * kv_row, kv_row},
                                         seqs, heads, lq, lk, d, mask == epona::Mask::Causal, additive ? &m : nullptr);
      log.record(shape("seqs", seqs, "heads", heads, "lq", lq, "lk", lk, "d", d,
                       mask == epona::Mask::Causal ? "causal" : "full", additive ? "additive-mask" : ""),
                 c.error(dout, ref));
    }
  });

  run_op<B, W>(ctx, "softmax_rows", kPointwise, 20, [&](Case<B>& c, OpLog& log) {
    if constexpr (HasSoftmaxRows<Ctx, A>) {
      for (const auto [rows, n] : kRows) {
        Vec x;
        auto dx = c.template in<A>(rows * n, x, -5.f, 5.f);
        softmax_rows(ctx, dx.data(), rows, n);
        log.record(shape("rows", rows, "n", n), c.error(dx, ops_ref::softmax_rows(x, rows, n)));
      }
    }
  });

  // Copies: copy, copy_rows (strided; the gaps of dst stay poisoned, so only rows are compared),
  // fill, convert, axpy (x float32 += a · v).
  run_op<B, W>(ctx, "copy", kPointwise, 21, [&](Case<B>& c, OpLog& log) {
    for (const i64 n : kLengths) {
      Vec x;
      auto dx = c.template in<A>(n, x);
      auto dy = c.template out<A>(n);
      copy(ctx, dx.data(), dy.data(), n);
      log.record(shape("n", n), c.error(dy, x));
    }
  });
  run_op<B, W>(ctx, "copy_rows", kPointwise, 22, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      const i64 src_stride = n + 3, dst_stride = n + 5;
      Vec x;
      auto dx = c.template in<A>(rows * src_stride, x);
      auto dy = c.template out<A>(rows * dst_stride);
      copy_rows(ctx, dx.data(), src_stride, dy.data(), dst_stride, rows, n);
      const auto got = c.get(dy);
      std::vector<float> kept;
      Vec ref;
      for (i64 r = 0; r < rows; ++r)
        for (i64 i = 0; i < n; ++i) kept.push_back(got[r * dst_stride + i]), ref.push_back(x[r * src_stride + i]);
      log.record(shape("rows", rows, "n", n), epona::test::rel_max(kept.data(), ref.data(), i64(kept.size())));
    }
  });
  run_op<B, W>(ctx, "fill", kPointwise, 23, [&](Case<B>& c, OpLog& log) {
    if constexpr (HasFill<Ctx, A>) {
      for (const i64 n : kLengths) {
        auto dy = c.template out<A>(n);
        fill(ctx, dy.data(), 0.75f, n);
        log.record(shape("n", n), c.error(dy, Vec(std::size_t(n), 0.75)));
      }
    }
  });
  run_op<B, W>(ctx, "convert", kPointwise, 24, [&](Case<B>& c, OpLog& log) {
    if constexpr (HasConvert<Ctx, A>) {
      for (const i64 n : kLengths) {
        Vec x;
        auto dx = c.template in<float>(n, x);
        auto dy = c.template out<A>(n);
        convert(ctx, dx.data(), dy.data(), n);
        log.record(shape("n", n, "f32->activation"), c.error(dy, x));
      }
    }
  });
  run_op<B, W>(ctx, "axpy", kPointwise, 25, [&](Case<B>& c, OpLog& log) {
    for (const i64 n : kLengths) {
      Vec x, v;
      auto dx = c.template in<float>(n, x);
      auto dv = c.template in<A>(n, v);
      axpy(ctx, dx.data(), dv.data(), -0.375f, n);
      log.record(shape("n", n), c.error(dx, ops_ref::axpy(x, v, -0.375)));
    }
  });

  // The DC-AE's ops on maps (NCHW on the CPU, channels-last on the GPU: Device<B>::channels_last).
  run_op<B, W>(ctx, "conv2d", kReduction, 26, [&](Case<B>& c, OpLog& log) {
    for (const auto [N, C, H, Wd, O, k, groups, with_bias, act] : kConvs) {
      const i64 HW = H * Wd, cg = C / groups;
      Vec x, w, b;
      c.template in<A>(N * C * HW, x);
      c.template in<W>(O * cg * k * k, w, -0.5f, 0.5f);
      auto db = c.template in<A>(O, b);
      auto dx = c.template put<A>(to_layout<B>(x, N, C, HW));
      // weights [O, C/g, k, k] (PyTorch) on the CPU, [O, k, k, C/g] channels-last.
      auto dw = c.template put<W>(to_layout<B>(w, O, cg, k * k));
      auto dy = c.template out<A>(N * O * HW);
      const epona::Conv2dShape s{N, C, H, Wd, O, k, groups};
      conv2d(ctx, dx.data(), dw.data(), with_bias ? db.data() : nullptr, dy.data(), s, act);
      const Vec ref = ops_ref::map(ops_ref::conv2d(x, N, C, H, Wd, w, with_bias ? &b : nullptr, O, k, groups),
                                   [act = act](double v) { return act_ref(act, v); });
      const auto got = c.get(dy);
      const Vec got_nchw = from_layout<B>(Vec(got.begin(), got.end()), N, O, HW);
      const std::vector<float> g(got_nchw.begin(), got_nchw.end());
      log.record(shape("N", N, "C", C, "H", H, "W", Wd, "O", O, "k", k, "groups", groups, with_bias ? "bias" : "no-bias",
                       label(act)),
                 epona::test::rel_max(g.data(), ref.data(), i64(g.size())));
    }
  });
  // residual += conv(x) + bias, no activation (a ResBlock's branch with its BatchNorm folded in).
  run_op<B, W>(ctx, "conv2d_residual", kReduction, 39, [&](Case<B>& c, OpLog& log) {
    if constexpr (HasConv2dResidual<Ctx, A>) {
      for (const auto [N, C, H, Wd, O, k, groups, with_bias, act] : kConvs) {
        (void)with_bias, (void)act;
        const i64 HW = H * Wd, cg = C / groups;
        Vec x, w, b, r;
        c.template in<A>(N * C * HW, x);
        c.template in<A>(O * cg * k * k, w, -0.5f, 0.5f);
        auto db = c.template in<A>(O, b);
        c.template in<A>(N * O * HW, r, -1.f, 1.f);
        auto dx = c.template put<A>(to_layout<B>(x, N, C, HW));
        auto dw = c.template put<A>(to_layout<B>(w, O, cg, k * k));
        auto dr = c.template put<A>(to_layout<B>(r, N, O, HW));
        conv2d_residual(ctx, dx.data(), dw.data(), db.data(), dr.data(), epona::Conv2dShape{N, C, H, Wd, O, k, groups});
        Vec ref = ops_ref::conv2d(x, N, C, H, Wd, w, &b, O, k, groups);
        for (std::size_t i = 0; i < ref.size(); ++i) ref[i] += r[i];
        log.record(shape("N", N, "C", C, "H", H, "W", Wd, "O", O, "k", k, "groups", groups),
                   c.error(dr, to_layout<B>(ref, N, O, HW)));
      }
    }
  });
  run_op<B, W>(ctx, "apply_conv_act", kPointwise, 27, [&](Case<B>& c, OpLog& log) {
    for (const i64 n : kLengths)
      for (const ConvAct act : kConvActs) {
        Vec x;
        auto dx = c.template in<A>(n, x, -4.f, 4.f);
        apply_conv_act(ctx, dx.data(), n, act);
        log.record(shape("n", n, label(act)), c.error(dx, ops_ref::map(x, [act = act](double v) { return act_ref(act, v); })));
      }
  });
  run_op<B, W>(ctx, "gated_act", kPointwise, 28, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows)
      for (const ConvAct act : {ConvAct::Relu, ConvAct::Silu}) {
        const i64 in_stride = 2 * n + 1, out_stride = n + 2;
        Vec v, g;
        auto dv = c.template in<A>(rows * in_stride, v, -3.f, 3.f);
        auto dg = c.template in<A>(rows * in_stride, g, -3.f, 3.f);
        auto dy = c.template out<A>(rows * out_stride);
        gated_act(ctx, dv.data(), dg.data(), dy.data(), rows, n, in_stride, out_stride, act);
        const auto got = c.get(dy);
        std::vector<float> kept;
        Vec ref;
        for (i64 r = 0; r < rows; ++r)
          for (i64 i = 0; i < n; ++i)
            kept.push_back(got[r * out_stride + i]), ref.push_back(v[r * in_stride + i] * act_ref(act, g[r * in_stride + i]));
        log.record(shape("rows", rows, "n", n, label(act)), epona::test::rel_max(kept.data(), ref.data(), i64(kept.size())));
      }
  });
  // A channel norm's input map and parameters (in the backend's map layout), and its float64
  // result: BatchNorm with running statistics, else RMSNorm2d.
  struct NormCase {
    Vec x, w, b, mean, var;
    Buf<B, A> dx;
    Buf<B, float> dw, db, dmean, dvar;
    Vec reference(i64 N, i64 C, i64 HW, bool batch, float eps) const {
      return batch ? ops_ref::batch_norm_2d(x, N, C, HW, w, b, mean, var, eps)
                   : ops_ref::rms_norm_2d(x, N, C, HW, w, b, eps);
    }
  };
  const auto norm_case = [&](Case<B>& c, i64 N, i64 C, i64 HW) {
    NormCase n;
    c.template in<A>(N * C * HW, n.x, -2.f, 3.f);
    n.dw = c.template in<float>(C, n.w, 0.5f, 1.5f);
    n.db = c.template in<float>(C, n.b);
    n.dmean = c.template in<float>(C, n.mean);
    n.dvar = c.template in<float>(C, n.var, 0.25f, 2.f);
    n.dx = c.template put<A>(to_layout<B>(n.x, N, C, HW));
    return n;
  };
  const auto norm2d = [&](const char* op, std::uint32_t seed, bool batch) {
    run_op<B, W>(ctx, op, kPointwise, seed, [&](Case<B>& c, OpLog& log) {
      for (const auto [N, C, HW] : kMaps) {
        const NormCase n = norm_case(c, N, C, HW);
        auto dy = c.template out<A>(N * C * HW);
        if (batch)
          batch_norm_2d(ctx, n.dx.data(), dy.data(), N, C, HW, n.dw.data(), n.db.data(), n.dmean.data(), n.dvar.data(),
                        eps);
        else
          rms_norm_2d(ctx, n.dx.data(), dy.data(), N, C, HW, n.dw.data(), n.db.data(), eps);
        const Vec ref = n.reference(N, C, HW, batch, eps);
        log.record(shape("N", N, "C", C, "HW", HW), c.error(dy, to_layout<B>(ref, N, C, HW)));
      }
    });
  };
  norm2d("rms_norm_2d", 29, false);
  norm2d("batch_norm_2d", 30, true);
  // residual += norm(branch) in one pass (BatchNorm with running statistics, else RMSNorm2d).
  const auto norm2d_add = [&](const char* op, std::uint32_t seed, bool batch) {
    run_op<B, W>(ctx, op, kPointwise, seed, [&](Case<B>& c, OpLog& log) {
      if constexpr (HasNorm2dAdd<Ctx, A>) {
        for (const auto [N, C, HW] : kMaps) {
          const NormCase n = norm_case(c, N, C, HW);
          Vec r;
          c.template in<A>(N * C * HW, r, -1.f, 1.f);
          auto dr = c.template put<A>(to_layout<B>(r, N, C, HW));
          norm_2d_add(ctx, n.dx.data(), dr.data(), N * HW, C, n.dw.data(), n.db.data(),
                      batch ? n.dmean.data() : nullptr, batch ? n.dvar.data() : nullptr, eps);
          Vec ref = n.reference(N, C, HW, batch, eps);
          for (std::size_t i = 0; i < ref.size(); ++i) ref[i] += r[i];
          log.record(shape("N", N, "C", C, "HW", HW), c.error(dr, to_layout<B>(ref, N, C, HW)));
        }
      }
    });
  };
  norm2d_add("norm_2d_add (RMSNorm2d)", 36, false);
  norm2d_add("norm_2d_add (BatchNorm2d)", 37, true);
  // RMSNorm without bias over float32 rows into the activation type (the temporal blocks' norms):
  // the map reference over C = n channels of one-pixel maps, no bias.
  run_op<B, W>(ctx, "rms_norm_rows", kPointwise, 38, [&](Case<B>& c, OpLog& log) {
    if constexpr (HasRmsNormRows<Ctx, A>) {
      for (const auto [rows, n] : kRows) {
        Vec x, w;
        auto dx = c.template in<float>(rows * n, x, -2.f, 3.f);
        auto dw = c.template in<float>(n, w, 0.5f, 1.5f);
        auto dy = c.template out<A>(rows * n);
        rms_norm_rows(ctx, dx.data(), dy.data(), rows, n, dw.data(), eps);
        log.record(shape("rows", rows, "n", n), c.error(dy, ops_ref::rms_norm_2d(x, rows, n, 1, w, Vec(n, 0.0), eps)));
      }
    }
  });
  const auto shuffle_op = [&](const char* op, std::uint32_t seed, bool up) {
    run_op<B, W>(ctx, op, kPointwise, seed, [&](Case<B>& c, OpLog& log) {
      for (const auto [N, C, H, Wd, r, Co] : up ? kShuffles : kUnshuffles) {
        Vec x;
        c.template in<A>(N * C * H * Wd, x);
        auto dx = c.template put<A>(to_layout<B>(x, N, C, H * Wd));
        const i64 out_hw = up ? H * Wd * r * r : H * Wd / (r * r);
        auto dy = c.template out<A>(N * Co * out_hw);
        const epona::ShuffleShape s{N, C, H, Wd, r};
        Vec ref;
        if (up) {
          pixel_shuffle_duplicate(ctx, dx.data(), dy.data(), s, Co);
          ref = ops_ref::duplicate_shortcut(x, N, C, H, Wd, r, Co);
        } else {
          pixel_unshuffle_average(ctx, dx.data(), dy.data(), s, Co);
          ref = ops_ref::average_shortcut(x, N, C, H, Wd, r, Co);
        }
        log.record(shape("N", N, "C", C, "H", H, "W", Wd, "r", r, "channels_out", Co),
                   c.error(dy, to_layout<B>(ref, N, Co, out_hw)));
      }
    });
  };
  shuffle_op("pixel_unshuffle_average", 31, false);
  shuffle_op("pixel_shuffle_duplicate", 32, true);
  // LiteMLA's ReLU linear attention over qkv maps (N, heads·3·d, HW), each evaluation order.
  run_op<B, W>(ctx, "relu_linear_attention", kReduction, 38, [&](Case<B>& c, OpLog& log) {
    for (const auto [N, heads, d, HW] : kLiteMla)
      for (const epona::AttentionOrder order : kMlaOrders) {
        const i64 C = heads * 3 * d;
        Vec qkv;
        c.template in<A>(N * C * HW, qkv);
        auto dqkv = c.template put<A>(to_layout<B>(qkv, N, C, HW));
        auto dout = c.template out<A>(N * heads * d * HW);
        relu_linear_attention(ctx, dqkv.data(), dout.data(), N, heads, d, HW, 1e-6f, order);
        const Vec ref = ops_ref::relu_linear_attention(qkv, N, heads, d, HW, 1e-6);
        log.record(shape("N", N, "heads", heads, "d", d, "HW", HW, "order", int(order)),
                   c.error(dout, to_layout<B>(ref, N, heads * d, HW)));
      }
  });
  run_op<B, W>(ctx, "transpose_last2", kPointwise, 33, [&](Case<B>& c, OpLog& log) {
    for (const auto [rows, n] : kRows) {
      const i64 N = 1 + rows % 2, A_ = rows, B_ = n;
      Vec x;
      auto dx = c.template in<A>(N * A_ * B_, x);
      auto dy = c.template out<A>(N * A_ * B_);
      transpose_last2(ctx, dx.data(), dy.data(), N, A_, B_);
      log.record(shape("N", N, "A", A_, "B", B_), c.error(dy, ops_ref::transpose_last2(x, N, A_, B_)));
    }
  });
}

}  // namespace ops_sweep
