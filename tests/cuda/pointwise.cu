// GPU tests for the memory-bound kernels: epona/cuda/pointwise/norm.cuh (LayerNorm, LayerNorm +
// modulation, residual add + LayerNorm, gated residual + modulated LayerNorm, per-head
// RMSNorm), rope.cuh, qk_rms_norm_rope.cuh, activation.cuh and elementwise.cuh, in float32,
// bf16 and the mixed storage combinations the model uses, against the CPU backend on the same
// (bf16-rounded) inputs. Outputs are poisoned first; in-place ops on packed buffers must leave
// every channel outside their heads bit-identical.
// Bounds: float32 1e-5 (rel_l2 and max|err|/max|ref|); bf16: 2^-8 of each value per rounding
// to bf16 (8 significant bits), counting the intermediate roundings the kernels share with
// PyTorch: 1 + scale in bf16 (modulate), (x · rrms) before · scale (QK-norm), and
// gate ⊙ y in bf16 before the residual add.
// Programmatic dependent launches: a chain of dependent kernels gives the host's bits exactly,
// eagerly and in a graph, with the launches on and off.
#include "cuda_test_util.cuh"
#include "epona/cuda/runtime/graph.hpp"
#include "epona/cuda/attention/qk_rms_norm_rope.cuh"
#include "epona/cuda/pointwise/copy_convert_axpy.cuh"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <vector>

using namespace epona;
using namespace epona::test;

namespace {

template <class TX, class TY, class TP>
std::string types() {
  return std::string(type_name<TX>()) + "->" + type_name<TY>() + " params " + type_name<TP>();
}

template <class TX, class TY, class TP>
void check_layer_norm(cuda::Context& ctx, std::int64_t rows, std::int64_t n, bool weight, bool bias, std::uint32_t seed) {
  cpu::Context cctx;
  HostF x = random_tensor({rows, n}, seed, 2.f, 4.f);  // a large mean tests the two-pass variance
  HostF w = random_tensor({n}, seed + 1, 0.5f, 1.5f), b = random_tensor({n}, seed + 2);
  round_to<TX>(x), round_to<TP>(w), round_to<TP>(b);
  HostF ref({rows, n});
  cpu::layer_norm(cctx, x.data(), ref.data(), rows, n, weight ? w.data() : nullptr, bias ? b.data() : nullptr, 1e-6f);
  auto dx = upload<TX>(ctx, x);
  auto dw = upload<TP>(ctx, w), db = upload<TP>(ctx, b);
  Dev<TY> dy({rows, n});
  poison(ctx, dy);
  cuda::layer_norm(ctx, dx.data(), dy.data(), rows, n, weight ? dw.data() : nullptr, bias ? db.data() : nullptr, 1e-6f);
  check_error(measure(download(ctx, dy), ref), one_rounding<TY>(max_abs(ref)),
              "layer_norm " + types<TX, TY, TP>() + " " + std::to_string(rows) + "x" + std::to_string(n) +
                  (weight ? " w" : "") + (bias ? " b" : ""));
}

template <class TX, class TY, class TP>
void check_modulate(cuda::Context& ctx, std::int64_t rows, std::int64_t n, std::uint32_t seed) {
  cpu::Context cctx;
  HostF x = random_tensor({rows, n}, seed, -3.f, 5.f);
  HostF shift = random_tensor({n}, seed + 1), scale = random_tensor({n}, seed + 2, -0.5f, 0.5f);
  round_to<TX>(x), round_to<TP>(shift), round_to<TP>(scale);
  HostF ref({rows, n});
  cpu::layer_norm_modulate(cctx, x.data(), ref.data(), rows, n, shift.data(), scale.data(), 1e-6f);
  auto dx = upload<TX>(ctx, x);
  auto dshift = upload<TP>(ctx, shift), dscale = upload<TP>(ctx, scale);
  Dev<TY> dy({rows, n});
  poison(ctx, dy);
  cuda::layer_norm_modulate(ctx, dx.data(), dy.data(), rows, n, dshift.data(), dscale.data(), 1e-6f);
  // bf16 parameters: 1 + scale is rounded (2^-8 |(1 + scale) LN(x)| <= 2^-8 (|ref| + |shift|)).
  Bound b = one_rounding<TY>(max_abs(ref));
  if (std::is_same_v<TP, bf16>) b = {b.rel + kBf16Roundoff * (1 + norm2(shift) * std::sqrt(double(rows)) / norm2(ref)),
                                     b.abs + kBf16Roundoff * (max_abs(ref) + max_abs(shift))};
  check_error(measure(download(ctx, dy), ref), b,
              "layer_norm_modulate " + types<TX, TY, TP>() + " " + std::to_string(rows) + "x" + std::to_string(n));
}

// An in-place per-head op on `heads` heads at the front of rows `stride` wide (packed QKV):
// the heads must match the CPU, every other channel must be untouched.
// roundings: how often a bf16 result is rounded (rms_norm_heads rounds x · rrms first).
template <class T, class GpuOp, class CpuOp>
void check_heads_inplace(cuda::Context& ctx, std::int64_t rows, std::int64_t stride, std::int64_t heads,
                         std::int64_t head_dim, std::uint32_t seed, const std::string& name, int roundings, GpuOp gpu,
                         CpuOp cpu_op) {
  HostF x = random_tensor({rows, stride}, seed, -2.f, 2.f);
  round_to<T>(x);
  HostF ref = x.clone();
  cpu_op(ref.data());
  auto dx = upload<T>(ctx, x);
  gpu(dx.data());
  const HostF out = download(ctx, dx);
  const auto in_heads = [&](std::int64_t i) { return i % stride < heads * head_dim; };
  Bound b = one_rounding<T>(max_abs(ref));
  b.rel *= roundings, b.abs *= roundings;
  check_error(measure(out.data(), ref.data(), out.numel(), in_heads), b,
              name + " " + type_name<T>() + " rows " + std::to_string(rows) + " heads " + std::to_string(heads) +
                  " x " + std::to_string(head_dim) + " stride " + std::to_string(stride));
  const std::int64_t changed =
      count_bit_differences(out.data(), x.data(), out.numel(), [&](std::int64_t i) { return !in_heads(i); });
  CHECK(changed == 0);
}

template <class T>
void check_rms_and_rope(cuda::Context& ctx, std::int64_t rows, std::int64_t heads, std::int64_t head_dim,
                        std::uint32_t seed) {
  cpu::Context cctx;
  const std::int64_t stride = 3 * heads * head_dim + 6;
  HostF scale = random_tensor({head_dim}, seed + 10, 0.5f, 1.5f);
  auto dscale = upload<float>(ctx, scale);
  check_heads_inplace<T>(
      ctx, rows, stride, heads, head_dim, seed, "rms_norm_heads", 2,
      [&](T* p) { cuda::rms_norm_heads(ctx, p, rows, stride, heads, head_dim, dscale.data(), 1e-6f); },
      [&](float* p) { cpu::rms_norm_heads(cctx, p, rows, stride, heads, head_dim, scale.data(), 1e-6f); });

  HostF angle = random_tensor({rows, head_dim / 2}, seed + 11, -20.f, 20.f);
  HostF cos({rows, head_dim / 2}), sin({rows, head_dim / 2});
  for (std::int64_t i = 0; i < angle.numel(); ++i) {
    cos.data()[i] = std::cos(angle.data()[i]);
    sin.data()[i] = std::sin(angle.data()[i]);
  }
  auto dcos = upload<float>(ctx, cos), dsin = upload<float>(ctx, sin);
  check_heads_inplace<T>(
      ctx, rows, stride, heads, head_dim, seed + 20, "apply_rope", 1,
      [&](T* p) { cuda::apply_rope(ctx, p, rows, stride, heads, head_dim, dcos.data(), dsin.data()); },
      [&](float* p) { cpu::apply_rope(cctx, p, rows, stride, heads, head_dim, cos.data(), sin.data()); });
}

// qk_norm_rope over row ranges of a packed [q | k | v | pad] buffer, each range with its own
// scales (queries of rows [q_first, end), keys of rows [first, end)): against the CPU's
// rms_norm_heads then apply_rope on the same rows (3 roundings in bf16: x·rrms, ·scale, the
// rotation), bit-identical to cuda::rms_norm_rope_heads per range and kind (what the model ran
// before), and every other channel untouched.
struct QkSegment {
  std::int64_t first, q_first, end;
  const float* q_scale = nullptr;
  const float* k_scale = nullptr;
};

template <class T>
void check_qk_norm_rope(cuda::Context& ctx, std::vector<QkSegment> segs, std::int64_t heads, std::int64_t head_dim,
                        std::uint32_t seed) {
  cpu::Context cctx;
  const std::int64_t rows = segs.back().end, width = heads * head_dim, stride = 3 * width + 6, pairs = head_dim / 2;
  HostF x = random_tensor({rows, stride}, seed, -2.f, 2.f);
  round_to<T>(x);
  HostF angle = random_tensor({rows, pairs}, seed + 1, -20.f, 20.f), cos({rows, pairs}), sin({rows, pairs});
  for (std::int64_t i = 0; i < angle.numel(); ++i) cos.data()[i] = std::cos(angle.data()[i]), sin.data()[i] = std::sin(angle.data()[i]);
  auto dcos = upload<float>(ctx, cos), dsin = upload<float>(ctx, sin);
  std::vector<HostF> scales;
  std::vector<Dev<float>> dscales;
  for (std::size_t i = 0; i < 2 * segs.size(); ++i) {
    scales.push_back(random_tensor({head_dim}, seed + 10 + std::uint32_t(i), 0.5f, 1.5f));
    dscales.push_back(upload<float>(ctx, scales.back()));
  }
  HostF ref = x.clone();
  std::vector<char> touched(static_cast<std::size_t>(x.numel()), 0);
  auto dref = upload<T>(ctx, x);
  for (std::size_t i = 0; i < segs.size(); ++i) {
    auto& g = segs[i];
    g.q_scale = dscales[2 * i].data(), g.k_scale = dscales[2 * i + 1].data();
    for (int kind = 0; kind < 2; ++kind) {
      const std::int64_t from = kind == 0 ? g.q_first : g.first, n = g.end - from, off = from * stride + kind * width;
      const HostF& sc = scales[2 * i + kind];
      cpu::rms_norm_heads(cctx, ref.data() + off, n, stride, heads, head_dim, sc.data(), 1e-6f);
      cpu::apply_rope(cctx, ref.data() + off, n, stride, heads, head_dim, cos.data() + from * pairs,
                      sin.data() + from * pairs);
      cuda::rms_norm_rope_heads(ctx, dref.data() + off, n, stride, heads, head_dim, dscales[2 * i + kind].data(),
                                1e-6f, dcos.data() + from * pairs, dsin.data() + from * pairs);
      for (std::int64_t r = from; r < g.end; ++r)
        for (std::int64_t c = 0; c < width; ++c) touched[r * stride + kind * width + c] = 1;
    }
  }
  auto dx = upload<T>(ctx, x);
  const std::string what = std::string("qk_norm_rope ") + type_name<T>() + " " + std::to_string(segs.size()) +
                           " segment(s), rows " + std::to_string(rows) + " heads " + std::to_string(heads) + " x " +
                           std::to_string(head_dim);
  if (segs.size() == 1)
    cuda::qk_norm_rope(ctx, dx.data(), stride, width, heads, head_dim, 1e-6f, dcos.data(), dsin.data(),
                       std::array<QkSegment, 1>{segs[0]});
  else
    cuda::qk_norm_rope(ctx, dx.data(), stride, width, heads, head_dim, 1e-6f, dcos.data(), dsin.data(),
                       std::array<QkSegment, 2>{segs[0], segs[1]});
  const HostF out = download(ctx, dx), per_range = download(ctx, dref);
  Bound b = one_rounding<T>(max_abs(ref));
  b.rel *= 3, b.abs *= 3;
  check_error(measure(out.data(), ref.data(), out.numel(), [&](std::int64_t i) { return touched[i] != 0; }), b, what);
  const std::int64_t differ = count_bit_differences(out, per_range);
  const std::int64_t changed =
      count_bit_differences(out.data(), x.data(), out.numel(), [&](std::int64_t i) { return !touched[i]; });
  MESSAGE(what, ": ", differ, " values differ from rms_norm_rope_heads per range, ", changed, " untouched changed");
  CHECK(differ == 0);
  CHECK(changed == 0);
}

// An in-place op over the first n of n + 1 elements: the guard element past n must survive.
template <class T, class GpuOp, class CpuOp>
void check_map_inplace(cuda::Context& ctx, std::int64_t n, std::uint32_t seed, const std::string& name, GpuOp gpu,
                       CpuOp cpu_op) {
  HostF x = random_tensor({n + 1}, seed, -6.f, 6.f);
  round_to<T>(x);
  HostF ref = x.clone();
  cpu_op(ref.data(), n);
  auto dx = upload<T>(ctx, x);
  gpu(dx.data(), n);
  const HostF out = download(ctx, dx);
  check_error(measure(out.data(), ref.data(), n, [](std::int64_t) { return true; }), one_rounding<T>(max_abs(ref)),
              name + " " + type_name<T>() + " n " + std::to_string(n));
  CHECK(std::memcmp(&out.data()[n], &x.data()[n], sizeof(float)) == 0);
}

template <class T>
void check_activations(cuda::Context& ctx, std::int64_t n, std::uint32_t seed) {
  cpu::Context cctx;
  check_map_inplace<T>(
      ctx, n, seed, "gelu_erf", [&](T* p, std::int64_t m) { cuda::gelu_erf(ctx, p, m); },
      [&](float* p, std::int64_t m) { cpu::gelu_erf(cctx, p, m); });
  check_map_inplace<T>(
      ctx, n, seed + 1, "gelu_tanh", [&](T* p, std::int64_t m) { cuda::gelu_tanh(ctx, p, m); },
      [&](float* p, std::int64_t m) { cpu::gelu_tanh(cctx, p, m); });
  check_map_inplace<T>(
      ctx, n, seed + 2, "silu", [&](T* p, std::int64_t m) { cuda::silu(ctx, p, m); },
      [&](float* p, std::int64_t m) { cpu::silu(cctx, p, m); });
  // silu_to writes a separate (poisoned) buffer and leaves its input alone.
  HostF x = random_tensor({n}, seed + 3, -6.f, 6.f);
  round_to<T>(x);
  HostF ref({n});
  cpu::silu_to(cctx, x.data(), ref.data(), n);
  auto dx = upload<T>(ctx, x);
  Dev<T> dy({n});
  poison(ctx, dy);
  cuda::silu_to(ctx, dx.data(), dy.data(), n);
  check_error(measure(download(ctx, dy), ref), one_rounding<T>(max_abs(ref)), std::string("silu_to ") + type_name<T>());
  CHECK(measure(download(ctx, dx), x).max_abs == 0);
}

// x (TX) += [gate (TG) ⊙] y (TY) over rows x n, and x += b (TG) per row.
template <class TX, class TY, class TG>
void check_residuals(cuda::Context& ctx, std::int64_t rows, std::int64_t n, std::uint32_t seed) {
  cpu::Context cctx;
  HostF x = random_tensor({rows, n}, seed), y = random_tensor({rows, n}, seed + 1), g = random_tensor({n}, seed + 2);
  round_to<TX>(x), round_to<TY>(y), round_to<TG>(g);
  const std::string t = types<TX, TY, TG>();
  {
    HostF ref = x.clone();
    cpu::add_inplace(cctx, ref.data(), y.data(), rows * n);
    auto dx = upload<TX>(ctx, x);
    auto dy = upload<TY>(ctx, y);
    cuda::add_inplace(ctx, dx.data(), dy.data(), rows * n);
    check_error(measure(download(ctx, dx), ref), one_rounding<TX>(max_abs(ref)), "add_inplace " + t);
  }
  {
    HostF ref = x.clone();
    cpu::add_gated(cctx, ref.data(), y.data(), g.data(), rows, n);
    auto dx = upload<TX>(ctx, x);
    auto dy = upload<TY>(ctx, y);
    auto dg = upload<TG>(ctx, g);
    cuda::add_gated(ctx, dx.data(), dy.data(), dg.data(), rows, n);
    Bound b = one_rounding<TX>(max_abs(ref));
    if (std::is_same_v<TG, bf16> && std::is_same_v<TY, bf16>) {  // gate ⊙ y is rounded to bf16 first
      HostF gy({rows, n});
      for (std::int64_t i = 0; i < gy.numel(); ++i) gy.data()[i] = g.data()[i % n] * y.data()[i];
      b = {b.rel + kBf16Roundoff * norm2(gy) / norm2(ref), b.abs + kBf16Roundoff * max_abs(gy)};
    }
    check_error(measure(download(ctx, dx), ref), b, "add_gated " + t);
  }
  {
    HostF ref = x.clone();
    cpu::add_row_broadcast(cctx, ref.data(), g.data(), rows, n);
    auto dx = upload<TX>(ctx, x);
    auto dg = upload<TG>(ctx, g);
    cuda::add_row_broadcast(ctx, dx.data(), dg.data(), rows, n);
    check_error(measure(download(ctx, dx), ref), one_rounding<TX>(max_abs(ref)), "add_row_broadcast " + t);
  }
}

// x (TX) += [gate (TG) ⊙] y (TY), then out (TO) = LN(x) affine (TP weight/bias) or modulated
// (TP shift/scale): the updated x is checked against the CPU's residual update, and out against
// the CPU's LayerNorm of the x the GPU stored (bf16 x is rounded before it is normalised, by
// design, as the unfused kernels do). offset > 0 misaligns x (the two-kernel fallback).
template <class TX, class TY, class TG, class TO, class TP>
void check_residual_norm(cuda::Context& ctx, std::int64_t rows, std::int64_t n, bool modulate, std::uint32_t seed,
                         std::int64_t offset = 0, bool separate = false) {
  cpu::Context cctx;
  HostF x = random_tensor({rows, n}, seed, -2.f, 3.f), y = random_tensor({rows, n}, seed + 1, -2.f, 2.f);
  HostF g = random_tensor({n}, seed + 2, -1.5f, 1.5f);
  HostF mul = random_tensor({n}, seed + 3, modulate ? -0.5f : 0.5f, modulate ? 0.5f : 1.5f);
  HostF add = random_tensor({n}, seed + 4);
  round_to<TX>(x), round_to<TY>(y), round_to<TG>(g), round_to<TP>(mul), round_to<TP>(add);
  HostF ref_x = x.clone();
  if (modulate) cpu::add_gated(cctx, ref_x.data(), y.data(), g.data(), rows, n);
  else cpu::add_inplace(cctx, ref_x.data(), y.data(), rows * n);
  // separate: the residual is read from src (misaligned by offset) and written to a poisoned x.
  auto src = upload<TX>(ctx, x, separate ? offset : 0);
  auto dx = separate ? Dev<TX>({rows, n}) : upload<TX>(ctx, x, offset);
  if (separate) poison(ctx, dx);
  auto dy = upload<TY>(ctx, y);
  auto dg = upload<TG>(ctx, g);
  auto dmul = upload<TP>(ctx, mul), dadd = upload<TP>(ctx, add);
  Dev<TO> dout({rows, n});
  poison(ctx, dout);
  if (modulate && separate)
    cuda::add_gated_layer_norm_modulate(ctx, static_cast<const TX*>(src.data()), dx.data(), dy.data(), dg.data(),
                                        dout.data(), rows, n, dadd.data(), dmul.data(), 1e-6f);
  else if (modulate)
    cuda::add_gated_layer_norm_modulate(ctx, dx.data(), dy.data(), dg.data(), dout.data(), rows, n, dadd.data(),
                                        dmul.data(), 1e-6f);
  else
    cuda::add_layer_norm(ctx, dx.data(), dy.data(), dout.data(), rows, n, dmul.data(), dadd.data(), 1e-5f);
  const std::string what = std::string(modulate ? "add_gated_layer_norm_modulate " : "add_layer_norm ") +
                           type_name<TX>() + "+=" + type_name<TY>() + " gate " + type_name<TG>() + " -> " +
                           type_name<TO>() + " params " + type_name<TP>() + " " + std::to_string(rows) + "x" +
                           std::to_string(n) + (offset ? " misaligned" : "") + (separate ? " from a separate input" : "");
  const HostF gx = download(ctx, dx);
  if (separate) CHECK(measure(download(ctx, src), x).max_abs == 0);  // the input stays as it was
  Bound bx = one_rounding<TX>(max_abs(ref_x));
  if (modulate && std::is_same_v<TG, bf16> && std::is_same_v<TY, bf16>) {  // gate ⊙ y is rounded to bf16 first
    HostF gy({rows, n});
    for (std::int64_t i = 0; i < gy.numel(); ++i) gy.data()[i] = g.data()[i % n] * y.data()[i];
    bx = {bx.rel + kBf16Roundoff * norm2(gy) / norm2(ref_x), bx.abs + kBf16Roundoff * max_abs(gy)};
  }
  check_error(measure(gx, ref_x), bx, what + " (residual)");
  HostF ref({rows, n});
  if (modulate) cpu::layer_norm_modulate(cctx, gx.data(), ref.data(), rows, n, add.data(), mul.data(), 1e-6f);
  else cpu::layer_norm(cctx, gx.data(), ref.data(), rows, n, mul.data(), add.data(), 1e-5f);
  Bound b = one_rounding<TO>(max_abs(ref));
  if (modulate && std::is_same_v<TP, bf16>)  // 1 + scale is rounded to bf16, as in check_modulate
    b = {b.rel + kBf16Roundoff * (1 + norm2(add) * std::sqrt(double(rows)) / norm2(ref)),
         b.abs + kBf16Roundoff * (max_abs(ref) + max_abs(add))};
  check_error(measure(download(ctx, dout), ref), b, what);
}

// qk_norm_rope over several items (QkItems: item b's rows `stride` apart, its RoPE rows
// `rope_stride` apart) in one launch against one launch per item: bit-identical (the row path and
// the head-per-warp path give the same bits), rows between the items untouched. Two segments
// (a double block's streams) or one with pruned queries (the last single block).
template <class T>
void check_qk_items(cuda::Context& ctx, std::int64_t count, std::int64_t heads, bool pruned, std::uint32_t seed) {
  const std::int64_t head_dim = 128, cond = 9, target = 7, rows = cond + target, stride = rows + 3;
  const std::int64_t width = heads * head_dim, row = 3 * width, pairs = head_dim / 2;
  const HostF x = random_tensor({count * stride, row}, seed, -2.f, 2.f);
  const HostF cos = random_tensor({count * rows, pairs}, seed + 1), sin = random_tensor({count * rows, pairs}, seed + 2);
  const auto dcos = upload<float>(ctx, cos), dsin = upload<float>(ctx, sin);
  const auto qs = upload<float>(ctx, random_tensor({head_dim}, seed + 3, 0.5f, 1.5f));
  const auto ks = upload<float>(ctx, random_tensor({head_dim}, seed + 4, 0.5f, 1.5f));
  const std::array<QkSegment, 2> two{QkSegment{0, 0, cond, qs.data(), ks.data()},
                                     QkSegment{cond, cond, rows, ks.data(), qs.data()}};
  const std::array<QkSegment, 1> one{QkSegment{0, cond, rows, qs.data(), ks.data()}};
  const auto run = [&](T* at, const float* c, const float* s, const QkItems& items) {
    if (pruned) cuda::qk_norm_rope(ctx, at, row, width, heads, head_dim, 1e-6f, c, s, one, items);
    else cuda::qk_norm_rope(ctx, at, row, width, heads, head_dim, 1e-6f, c, s, two, items);
  };
  auto together = upload<T>(ctx, x), apart = upload<T>(ctx, x);
  run(together.data(), dcos.data(), dsin.data(), QkItems{count, stride, rows});
  for (std::int64_t b = 0; b < count; ++b)
    run(apart.data() + b * stride * row, dcos.data() + b * rows * pairs, dsin.data() + b * rows * pairs, {});
  const HostF t = download(ctx, together), a = download(ctx, apart);
  CAPTURE(std::string(type_name<T>()) + " " + std::to_string(count) + " items, " + std::to_string(heads) + " heads" +
          (pruned ? ", pruned queries" : ", two segments"));
  CHECK(count_bit_differences(t, a) == 0);
  CHECK(count_bit_differences(t, x) > 0);  // it did work
}

// The item forms (a DiT's folded batch: the same rows of several items, each with its own
// vectors) against the one-item kernels called item by item on the same buffers. Bit-identical
// where both take the same kernel; where the items' rows together reach the warp-per-row kernel
// and one item's do not (`same_kernel` false), the sums run in another order: float32 within
// 1e-6 of the largest value, bf16 within one flipped rounding (one ulp, 2^-7 of the largest
// value's binade). `rows` rows per item, `stride` rows
// between items' outputs, inputs read from a separate contiguous buffer (x_stride = rows) or in
// place (x_stride = stride); the rows between items must stay as they were.
template <class T>
void check_norm_items(cuda::Context& ctx, std::int64_t count, std::int64_t rows, std::int64_t stride, std::int64_t n,
                      bool separate, std::uint32_t seed, bool same_kernel = true) {
  const std::int64_t mod_stride = 5 * n, x_stride = separate ? rows : stride;
  const NormItems items{count, rows, stride, x_stride, mod_stride};
  HostF x = random_tensor({count * stride, n}, seed, -2.f, 3.f), src = random_tensor({count * rows, n}, seed + 1);
  HostF y = random_tensor({count * stride, n}, seed + 2), vecs = random_tensor({count * mod_stride}, seed + 3, -0.5f, 0.5f);
  const auto dsrc = upload<T>(ctx, src), dy = upload<T>(ctx, y), dv = upload<T>(ctx, vecs);
  const T* v = dv.data();  // item 0's gate, shift and scale at v, v + n, v + 2n
  const std::string what = std::string(type_name<T>()) + " " + std::to_string(count) + " items of " +
                           std::to_string(rows) + " rows (stride " + std::to_string(stride) + ") x " +
                           std::to_string(n) + (separate ? ", from a separate input" : ", in place");
  // Two runs over poisoned outputs (and the same residual): the item form, then item by item.
  const auto run = [&](bool one_launch, bool residual) {
    auto dx = upload<T>(ctx, x);
    Dev<T> out({count * stride, n});
    poison(ctx, out);
    const T* in = separate ? dsrc.data() : dx.data();
    if (one_launch && residual)
      cuda::add_gated_layer_norm_modulate_items(ctx, in, dx.data(), dy.data(), v, out.data(), n, v + n, v + 2 * n, 1e-6f,
                                                items);
    else if (one_launch)
      cuda::layer_norm_modulate_items(ctx, in, out.data(), n, v + n, v + 2 * n, 1e-6f, items);
    for (std::int64_t b = 0; !one_launch && b < count; ++b) {
      const std::int64_t at = b * stride * n, m = b * mod_stride;
      const T* xb = in + b * x_stride * n;
      if (residual)
        cuda::add_gated_layer_norm_modulate(ctx, xb, dx.data() + at, dy.data() + at, v + m, out.data() + at, rows, n,
                                            v + m + n, v + m + 2 * n, 1e-6f);
      else
        cuda::layer_norm_modulate(ctx, xb, out.data() + at, rows, n, v + m + n, v + m + 2 * n, 1e-6f);
    }
    return std::pair{download(ctx, dx), download(ctx, out)};
  };
  for (const bool residual : {false, true}) {
    const auto [x1, o1] = run(true, residual);
    const auto [x2, o2] = run(false, residual);
    CAPTURE(what);
    CAPTURE(residual);
    if (same_kernel) {
      CHECK(count_bit_differences(o1, o2) == 0);
      CHECK(count_bit_differences(x1, x2) == 0);  // the residual (and the gap rows) alike
    } else {
      const double limit = std::is_same_v<T, float> ? 1e-6 : 2 * kBf16Roundoff;
      CHECK(measure(o1, o2).max_abs <= limit * max_abs(o2));
      CHECK(count_bit_differences(x1, x2) == 0);  // the residual update is element-wise: exact
    }
  }
}

}  // namespace

TEST_CASE("cuda add_layer_norm and add_gated_layer_norm_modulate match the CPU's add then norm") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 700;
  // Widths: the MST's 2048 and the DiTs' 1024 (8 and 4 packs per lane of a warp), 520 (a
  // partial last pack round), 64 (one pack per lane, most lanes idle), 45 (not packable: the
  // two-kernel fallback). 9 rows take the block-per-row kernel, 1500 the warp-per-row one (at
  // least 8 rows per SM); 8192 is wider than a warp holds (block per row at any count).
  for (std::int64_t rows : {9, 1500})
    for (std::int64_t n : {2048, 1024, 520, 64, 45, 8192}) {
      check_residual_norm<float, float, float, float, float>(ctx, rows, n, false, seed++);
      check_residual_norm<float, bf16, float, bf16, float>(ctx, rows, n, false, seed++);  // the MST's mix
      check_residual_norm<float, float, float, float, float>(ctx, rows, n, true, seed++);
      check_residual_norm<bf16, bf16, bf16, bf16, bf16>(ctx, rows, n, true, seed++);      // the DiTs' mix
    }
  check_residual_norm<float, bf16, float, bf16, float>(ctx, 5150, 2048, false, seed++);  // the MST's rows
  check_residual_norm<bf16, bf16, bf16, bf16, bf16>(ctx, 515, 1024, true, seed++);      // the TrajDiT's
  check_residual_norm<float, bf16, float, bf16, float>(ctx, 7, 2048, false, seed++, 1);  // misaligned x
  check_residual_norm<bf16, bf16, bf16, bf16, bf16>(ctx, 7, 1024, true, seed++, 2);
  // Residual read from one buffer, updated into another (a DiT's first block on cond_in's rows):
  // both kernels, and the fallback (misaligned input: copy, then the in-place pair).
  check_residual_norm<bf16, bf16, bf16, bf16, bf16>(ctx, 515, 1024, true, seed++, 0, true);
  check_residual_norm<bf16, bf16, bf16, bf16, bf16>(ctx, 1500, 2048, true, seed++, 0, true);
  check_residual_norm<float, float, float, float, float>(ctx, 9, 1024, true, seed++, 0, true);
  check_residual_norm<bf16, bf16, bf16, bf16, bf16>(ctx, 7, 1024, true, seed++, 2, true);
}

namespace {

// The MST's token assembly (try_assemble_frame_tokens) against a float64 loop over the same
// (TI-rounded) inputs. Action rows are a single float32 add: bit-exact. Image rows: one
// LayerNorm rounded to float32, then the add.
template <class TI>
void check_frame_tokens(cuda::Context& ctx, const FrameTokens& t, bool affine, std::uint32_t seed) {
  const std::int64_t F = t.frames, L = t.image_rows, A = t.actions, C = t.width, T = t.tokens();
  HostF image = random_tensor({F * L, C}, seed, -2.f, 4.f), actions = random_tensor({A, t.action_entries, C}, seed + 1);
  HostF te = random_tensor({F, C}, seed + 2), w = random_tensor({C}, seed + 3, 0.5f, 1.5f);
  HostF b = random_tensor({C}, seed + 4);
  round_to<TI>(image);
  HostF ref({F, T, C});
  for (std::int64_t f = 0; f < F; ++f) {
    for (std::int64_t s = 0; s < A; ++s)
      for (std::int64_t c = 0; c < C; ++c)
        ref.at(f, s, c) = actions.at(s, f, c) + te.at(f, c);
    for (std::int64_t l = 0; l < L; ++l) {
      const float* x = image.data() + (f * L + l) * C;
      double mean = 0, var = 0;
      for (std::int64_t c = 0; c < C; ++c) mean += x[c];
      mean /= double(C);
      for (std::int64_t c = 0; c < C; ++c) var += (x[c] - mean) * (x[c] - mean);
      const double rstd = 1 / std::sqrt(var / double(C) + t.eps);
      for (std::int64_t c = 0; c < C; ++c) {
        const double y = (x[c] - mean) * rstd;
        ref.at(f, A + l, c) = float(float(affine ? y * w.data()[c] + b.data()[c] : y) + te.at(f, c));
      }
    }
  }
  auto dimage = upload<TI>(ctx, image);
  auto dactions = upload<float>(ctx, actions), dte = upload<float>(ctx, te), dw = upload<float>(ctx, w);
  auto db = upload<float>(ctx, b);
  Dev<float> out({F, T, C});
  poison(ctx, out);
  REQUIRE(cuda::try_assemble_frame_tokens(ctx, dimage.data(), dactions.data(), dte.data(), affine ? dw.data() : nullptr,
                                          affine ? db.data() : nullptr, out.data(), t));
  const HostF got = download(ctx, out);
  const std::string what = std::string("frame tokens ") + type_name<TI>() + " " + std::to_string(F) + "x(" +
                           std::to_string(A) + "+" + std::to_string(L) + ")x" + std::to_string(C) +
                           (affine ? " affine" : "");
  const auto action_row = [&](std::int64_t i) { return (i / C) % T < A; };
  CHECK(count_bit_differences(got.data(), ref.data(), got.numel(), action_row) == 0);
  const auto image_row = [&](std::int64_t i) { return !action_row(i); };
  const Diff e = measure(got.data(), ref.data(), got.numel(), image_row);
  check_error(e, one_rounding<float>(e.max_ref), what);
}

}  // namespace

TEST_CASE("cuda assemble_frame_tokens: the MST's tokens in one pass, against float64") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 900;
  // The MST's window (10 frames of 3 action + 512 image rows, 11 action entries, width 2048) in
  // both pass orders, then small widths (one and a partial pack round per lane) and no actions.
  for (bool reverse : {true, false}) {
    ctx.policy().reversed_passes = reverse;
    check_frame_tokens<bf16>(ctx, {10, 512, 3, 11, 2048, 1e-5f}, true, seed++);
    check_frame_tokens<float>(ctx, {10, 512, 3, 11, 2048, 1e-5f}, true, seed++);
  }
  ctx.policy().reversed_passes = true;
  check_frame_tokens<float>(ctx, {3, 5, 3, 4, 64, 1e-6f}, false, seed++);
  check_frame_tokens<bf16>(ctx, {2, 7, 1, 2, 520, 1e-5f}, true, seed++);
  check_frame_tokens<float>(ctx, {4, 9, 0, 0, 128, 1e-5f}, true, seed++);
}

TEST_CASE("cuda assemble_frame_tokens declines layouts it cannot pack and rejects bad arguments") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  Dev<float> image({6, 48}), actions({3, 3, 48}), te({2, 48}), out({2, 6, 48});
  poison(ctx, out);
  // Width 45 is not a multiple of 8: nothing is written and the caller composes the passes.
  CHECK_FALSE(cuda::try_assemble_frame_tokens(ctx, image.data(), actions.data(), te.data(), nullptr, nullptr,
                                              out.data(), FrameTokens{2, 3, 3, 3, 45, 1e-5f}));
  const HostF untouched = download(ctx, out);
  CHECK(std::count_if(untouched.data(), untouched.data() + untouched.numel(), [](float v) { return std::isnan(v); }) ==
        untouched.numel());
  // A misaligned output row start declines too.
  CHECK_FALSE(cuda::try_assemble_frame_tokens(ctx, image.data(), actions.data(), te.data(), nullptr, nullptr,
                                              out.data() + 1, FrameTokens{2, 3, 3, 3, 40, 1e-5f}));
  const FrameTokens ok{2, 3, 3, 3, 48, 1e-5f};
  CHECK_THROWS_AS(cuda::try_assemble_frame_tokens(ctx, image.data(), static_cast<const float*>(nullptr), te.data(),
                                                  nullptr, nullptr, out.data(), ok),
                  Error);
  CHECK_THROWS_AS(cuda::try_assemble_frame_tokens(ctx, image.data(), actions.data(), te.data(), nullptr, nullptr,
                                                  out.data(), FrameTokens{3, 2, 3, 2, 48, 1e-5f}),
                  Error);  // 2 action entries for 3 frames
  CHECK_THROWS_AS(cuda::try_assemble_frame_tokens(ctx, image.data(), actions.data(), te.data(), nullptr, nullptr,
                                                  out.data(), FrameTokens{-1, 3, 3, 3, 48, 1e-5f}),
                  Error);
  ctx.synchronize();
}

TEST_CASE("cuda layer_norm matches cpu::layer_norm") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 1;
  for (std::int64_t n : {2048, 1000, 33, 8192})  // 8192: wider than the warp-per-row kernel holds
    for (int affine = 0; affine < 4; ++affine) {
      check_layer_norm<float, float, float>(ctx, 7, n, affine & 1, affine & 2, seed++);
      check_layer_norm<bf16, bf16, float>(ctx, 7, n, affine & 1, affine & 2, seed++);
      check_layer_norm<float, bf16, float>(ctx, 7, n, affine & 1, affine & 2, seed++);
    }
  check_layer_norm<float, float, float>(ctx, 5150, 2048, false, false, seed++);  // the MST's rows (warp per row)
  for (std::int64_t n : {2048, 1000, 64}) {
    check_layer_norm<bf16, bf16, float>(ctx, 1500, n, true, true, seed++);
    check_layer_norm<float, bf16, float>(ctx, 1500, n, true, true, seed++);
    check_modulate<bf16, bf16, bf16>(ctx, 1500, n, seed++);
  }
  // In place (x and y alias), as the CPU allows.
  cpu::Context cctx;
  HostF x = random_tensor({9, 300}, 99, -1.f, 3.f);
  HostF ref({9, 300});
  cpu::layer_norm(cctx, x.data(), ref.data(), 9, 300, nullptr, nullptr, 1e-5f);
  auto dx = upload<float>(ctx, x);
  cuda::layer_norm(ctx, dx.data(), dx.data(), 9, 300, static_cast<const float*>(nullptr), nullptr, 1e-5f);
  check_error(measure(download(ctx, dx), ref), one_rounding<float>(max_abs(ref)), "layer_norm in place");
}

TEST_CASE("cuda layer_norm_modulate matches cpu::layer_norm_modulate") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 200;
  for (std::int64_t n : {2048, 1024, 64, 45}) {
    check_modulate<float, float, float>(ctx, 11, n, seed++);
    check_modulate<bf16, bf16, bf16>(ctx, 11, n, seed++);
    check_modulate<float, bf16, bf16>(ctx, 11, n, seed++);
    check_modulate<bf16, bf16, float>(ctx, 11, n, seed++);
  }
}

TEST_CASE_TEMPLATE("cuda rms_norm_heads and apply_rope on packed QKV", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_rms_and_rope<T>(ctx, 19, 3, 24, 300);
  check_rms_and_rope<T>(ctx, 33, 2, 128, 310);
  check_rms_and_rope<T>(ctx, 5, 1, 4, 320);
  check_rms_and_rope<T>(ctx, 515, 16, 128, 330);
}

TEST_CASE_TEMPLATE("cuda qk_norm_rope: queries and keys of several row ranges in one launch", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  // A TrajDiT double block (condition rows, trajectory rows: two scales each), its pruned
  // single block (keys of all rows, queries of the last 15), a VisDiT double block, and a
  // generic head dim (fewer pairs than lanes) with an empty query range.
  check_qk_norm_rope<T>(ctx, {{0, 0, 515}, {515, 515, 530}}, 8, 128, 900);
  check_qk_norm_rope<T>(ctx, {{0, 515, 530}}, 8, 128, 910);
  check_qk_norm_rope<T>(ctx, {{0, 0, 515}, {515, 515, 1027}}, 16, 128, 920);
  check_qk_norm_rope<T>(ctx, {{0, 0, 7}, {7, 19, 19}}, 3, 24, 930);
}

TEST_CASE_TEMPLATE("cuda activations match the CPU", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_activations<T>(ctx, 1001, 400);
  check_activations<T>(ctx, 1 << 20, 410);
  check_activations<T>(ctx, 8 * 100003, 420);  // packs not a multiple of the block
}

TEST_CASE("cuda residual updates match the CPU (PyTorch promotion for mixed types)") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_residuals<float, float, float>(ctx, 13, 2048, 500);
  check_residuals<bf16, bf16, bf16>(ctx, 13, 2048, 510);
  check_residuals<float, bf16, bf16>(ctx, 13, 2048, 520);
  check_residuals<float, float, float>(ctx, 3, 7, 530);
  check_residuals<bf16, bf16, bf16>(ctx, 3, 7, 540);
}

TEST_CASE("cuda pointwise kernels reject bad arguments with epona::Error") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  Dev<float> x({64}), t({8});
  CHECK_THROWS_WITH_AS(cuda::apply_rope(ctx, x.data(), 2, 32, 2, 5, t.data(), t.data()),
                       doctest::Contains("even"), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::rms_norm_heads(ctx, x.data(), 2, 10, 2, 8, t.data(), 1e-6f),
                       doctest::Contains("row stride"), epona::Error);
  CHECK_THROWS_AS(cuda::layer_norm(ctx, x.data(), x.data(), 2, 0, t.data(), t.data(), 1e-6f), epona::Error);
  const QkSegment bad{4, 2, 6, t.data(), t.data()};  // queries start before the range
  CHECK_THROWS_WITH_AS(cuda::qk_norm_rope(ctx, x.data(), 8, 4, 1, 4, 1e-6f, t.data(), t.data(),
                                          std::array<QkSegment, 1>{bad}),
                       doctest::Contains("segment"), epona::Error);
  const QkSegment ok{0, 0, 2, t.data(), t.data()};
  CHECK_THROWS_WITH_AS(cuda::qk_norm_rope(ctx, x.data(), 8, 6, 1, 4, 1e-6f, t.data(), t.data(),
                                          std::array<QkSegment, 1>{ok}),
                       doctest::Contains("key offset"), epona::Error);
  CHECK_THROWS_AS(cuda::add_gated(ctx, x.data(), x.data(), t.data(), -1, 8), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::add_layer_norm(ctx, x.data(), static_cast<const float*>(nullptr), t.data(), 1, 8,
                                            t.data(), t.data(), 1e-5f),
                       doctest::Contains("null"), epona::Error);
  CHECK_THROWS_WITH_AS(cuda::add_gated_layer_norm_modulate(ctx, x.data(), x.data(), static_cast<const float*>(nullptr),
                                                           t.data(), 1, 8, t.data(), t.data(), 1e-6f),
                       doctest::Contains("null gate"), epona::Error);
  CHECK_THROWS_AS(cuda::add_layer_norm(ctx, x.data(), x.data(), t.data(), 1, 0, t.data(), t.data(), 1e-5f),
                  epona::Error);
}

// Programmatic dependent launch (detail::launch_after): a kernel may be scheduled while the one
// before it in the stream still runs, and must wait for it before reading. A chain of 80
// dependent kernels (x -> bf16 copy -> x += round(a · copy), 40 times; 4M elements, so each kernel
// spans several waves and a consumer that did not wait would read stale values) must give the
// host's bits exactly, eagerly and recorded in a graph, with the launches on and off.
TEST_CASE("cuda programmatic dependent launches: each kernel of a chain sees what the one before wrote") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const std::int64_t n = std::int64_t{1} << 22;
  constexpr int kSteps = 40;
  constexpr float kA = 0.25f;
  const HostF x0 = random_tensor({n}, 991, -1.f, 1.f);
  HostF ref = x0.clone();
  for (int k = 0; k < kSteps; ++k)
    for (std::int64_t i = 0; i < n; ++i) {
      const float v = float(bf16(ref.data()[i]));
      ref.data()[i] = ref.data()[i] + float(bf16(kA * v));
    }
  const auto run = [&](bool programmatic, bool graph) {
    ctx.policy().programmatic_launch = programmatic;
    auto x = upload<float>(ctx, x0);
    Dev<bf16> xb({n});
    const auto chain = [&] {
      for (int k = 0; k < kSteps; ++k) {
        cuda::convert(ctx, x.data(), xb.data(), n);
        cuda::axpy(ctx, x.data(), xb.data(), kA, n);
      }
    };
    if (graph) {
      cuda::GraphCache recorded;  // the samplers' graph path (EPONA_CUDA_GRAPHS=0: runs directly)
      recorded.run(ctx, {1}, chain);
      CHECK(recorded.captures() == (ctx.policy().graphs ? 1 : 0));
    } else {
      chain();
    }
    return download(ctx, x);
  };
  for (const bool graph : {false, true})
    for (const bool programmatic : {true, false}) {
      const HostF out = run(programmatic, graph);
      const std::int64_t differ = count_bit_differences(out, ref);
      CHECK_MESSAGE(differ == 0, (graph ? "graph" : "eager"), (programmatic ? ", programmatic" : ", plain"), ": ",
                    differ, " of ", n, " elements differ from the host");
    }
}

TEST_CASE_TEMPLATE("cuda item norms: several items' rows with their own vectors in one launch, as item by item", T,
                   float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  for (const bool separate : {false, true}) {
    check_norm_items<T>(ctx, 3, 5, 7, 256, separate, 11);      // a block per row, gaps between items
    check_norm_items<T>(ctx, 4, 515, 518, 1024, separate, 12, false);  // the items reach the warp kernel
    check_norm_items<T>(ctx, 2, 4, 6, 100, separate, 13);       // unpackable width: item by item
  }
}

TEST_CASE_TEMPLATE("cuda qk_norm_rope over several items in one launch, as one launch per item", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  for (const bool pruned : {false, true}) {
    check_qk_items<T>(ctx, 3, 2, pruned, 21);    // few heads: head per warp
    check_qk_items<T>(ctx, 40, 16, pruned, 22);  // many: the row path in bf16
  }
}
