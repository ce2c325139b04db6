// epona/cpu/conv.hpp — the NCHW float32 kernels of the convolutional autoencoder (DC-AE):
// 2-D convolution (stride 1, "same" zero padding, groups) as GEMMs — Winograd F(2x2, 3x3) for
// the large 3x3 ones (conv_winograd.hpp), else the packed micro-kernels of gemm_kernels.hpp
// with im2col done while packing (no panel in memory), or Eigen over im2col panels on the
// generic path — depthwise convolution as direct loops, ReLU/SiLU
// epilogues, per-pixel channel norms (RMSNorm2d, eval BatchNorm2d), the GLU gate and
// LiteMLA's ReLU linear attention.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "epona/core/shapes.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/activation.hpp"
#include "epona/cpu/conv_winograd.hpp"
#include "epona/cpu/gemm.hpp"

namespace epona::cpu {

namespace conv_detail {
// act(v) for one value: ReLU, SiLU = v / (1 + e^-v), or identity.
inline float activate(float v, ConvAct act) {
  switch (act) {
    case ConvAct::Relu: return v > 0.f ? v : 0.f;
    case ConvAct::Silu: return v / (1.0f + std::exp(-v));
    case ConvAct::None: break;
  }
  return v;
}
}  // namespace conv_detail

inline void apply_conv_act(Context&, float* x, std::int64_t n, ConvAct act) {
  if (act == ConvAct::None) return;
#pragma omp parallel for
  for (std::int64_t i = 0; i < n; ++i) x[i] = conv_detail::activate(x[i], act);
}

namespace conv_detail {
using RowMat = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using CMap = Eigen::Map<const RowMat>;
using CStridedMap = Eigen::Map<const RowMat, 0, Eigen::OuterStride<>>;
using StridedMap = Eigen::Map<RowMat, 0, Eigen::OuterStride<>>;

// Per-thread im2col panel bound (floats, 4 MB): keeps a task's panel near the core's caches.
inline constexpr std::int64_t kPanelFloats = std::int64_t{1} << 20;
// Narrowest task worth its own GEMM (output columns), and tasks per thread for load balance.
inline constexpr std::int64_t kMinTaskColumns = 256;
inline constexpr std::int64_t kTasksPerThread = 2;

// Weights as float32: a view for float, a widened copy for bf16 (accumulation stays fp32).
template <class W>
const float* weights_as_float(const W* w, std::int64_t n, std::vector<float>& storage) {
  if constexpr (std::is_same_v<W, float>) {
    return w;
  } else {
    storage.resize(static_cast<std::size_t>(n));
#pragma omp parallel for
    for (std::int64_t i = 0; i < n; ++i) storage[static_cast<std::size_t>(i)] = float(w[i]);
    return storage.data();
  }
}

// panel[(c*k + dy)*k + dx, (y - y0)*W + x] = in[c, y + dy - k/2, x + dx - k/2] (0 outside),
// for output rows y in [y0, y0 + rows) of one image and channels c of one group.
inline void im2col(const float* in, std::int64_t channels, std::int64_t H, std::int64_t W, std::int64_t k,
                   std::int64_t y0, std::int64_t rows, float* panel) {
  const std::int64_t pad = k / 2, P = rows * W, K = channels * k * k;
  for (std::int64_t kr = 0; kr < K; ++kr) {
    const std::int64_t c = kr / (k * k), dy = (kr / k) % k - pad, dx = kr % k - pad;
    const float* plane = in + c * H * W;
    float* dst = panel + kr * P;
    const std::int64_t x_lo = std::max<std::int64_t>(0, -dx), x_hi = std::min(W, W - dx);
    for (std::int64_t r = 0; r < rows; ++r) {
      const std::int64_t ys = y0 + r + dy;
      float* d = dst + r * W;
      if (ys < 0 || ys >= H || x_lo >= x_hi) {
        std::fill_n(d, W, 0.f);
        continue;
      }
      const float* src = plane + ys * W + dx;
      std::fill_n(d, x_lo, 0.f);
      std::copy(src + x_lo, src + x_hi, d + x_lo);
      std::fill(d + x_hi, d + W, 0.f);
    }
  }
}

// How one image-group's output (cout x H·W) is cut into independent tasks: blocks of whole
// output rows (bounded by the panel size), and, when that leaves too few tasks for the
// threads (small maps), blocks of output channels as well.
struct Tiling {
  std::int64_t rows = 1, row_tasks = 1, channels = 1, channel_tasks = 1;
  std::int64_t tasks() const { return row_tasks * channel_tasks; }
};

inline Tiling tile(std::int64_t cout, std::int64_t K, std::int64_t H, std::int64_t W, bool panel, std::int64_t threads) {
  Tiling t;
  const std::int64_t want = std::max<std::int64_t>(1, threads * kTasksPerThread);
  const std::int64_t by_panel = panel ? std::max<std::int64_t>(1, kPanelFloats / (K * W)) : H;
  const std::int64_t by_balance = std::max<std::int64_t>((H + want - 1) / want, (kMinTaskColumns + W - 1) / W);
  t.rows = std::clamp<std::int64_t>(std::min(by_panel, by_balance), 1, H);
  t.row_tasks = (H + t.rows - 1) / t.rows;
  const std::int64_t split = threads > 1 ? std::max<std::int64_t>(1, want / t.row_tasks) : 1;
  t.channels = std::max<std::int64_t>(1, (cout + split - 1) / split);
  t.channels = std::min(cout, (t.channels + 15) / 16 * 16);  // whole SIMD-friendly row blocks
  t.channel_tasks = (cout + t.channels - 1) / t.channels;
  return t;
}

// out[o, p] = act(bias[o] + Σ_k W[o, k] · in[k, p]) for one group of one image. Every task runs
// its own im2col (k > 1) and a single-threaded GEMM, then its epilogue while the block is hot.
inline void conv_group(const float* in, std::int64_t cin, std::int64_t H, std::int64_t W, std::int64_t k,
                       const float* w, const float* bias, std::int64_t cout, float* out, ConvAct act,
                       std::int64_t threads) {
  const std::int64_t HW = H * W, K = cin * k * k;
  const Tiling t = tile(cout, K, H, W, k > 1, threads);
#pragma omp parallel num_threads(static_cast<int>(std::min(threads, t.tasks())))
  {
    std::vector<float> panel(k > 1 ? static_cast<std::size_t>(K * t.rows * W) : 0);
#pragma omp for schedule(dynamic)
    for (std::int64_t task = 0; task < t.tasks(); ++task) {
      const std::int64_t y0 = (task % t.row_tasks) * t.rows, rows = std::min(t.rows, H - y0), P = rows * W;
      const std::int64_t o0 = (task / t.row_tasks) * t.channels, no = std::min(t.channels, cout - o0);
      StridedMap Y(out + o0 * HW + y0 * W, no, P, Eigen::OuterStride<>(HW));
      const CMap Wm(w + o0 * K, no, K);
      if (k == 1) {
        Y.noalias() = Wm * CStridedMap(in + y0 * W, cin, P, Eigen::OuterStride<>(HW));
      } else {
        im2col(in, cin, H, W, k, y0, rows, panel.data());
        Y.noalias() = Wm * CMap(panel.data(), K, P);
      }
      for (std::int64_t o = 0; o < no; ++o) {
        float* row = out + (o0 + o) * HW + y0 * W;
        const float b = bias ? bias[o0 + o] : 0.f;
        for (std::int64_t p = 0; p < P; ++p) row[p] = activate(row[p] + b, act);
      }
    }
  }
}

// The right operand of a convolution as a GEMM, B[K×P] = im2col(in) (K = C·k·k, P = H·W), packed
// straight from the image: panel columns are consecutive pixels, cut into runs along image
// rows (one run per panel when the width is a multiple of the tile, the usual case).
struct PackIm2col {
  const float* in;
  std::int64_t H, W, k, nr;

  // d[0, cols) = row[x0 + dx + j] for pixels j of image row `ys` (zero outside the image).
  void copy_shifted(const float* plane, std::int64_t ys, std::int64_t x0, std::int64_t dx, std::int64_t cols,
                    float* d) const {
    if (ys < 0 || ys >= H) {
      std::fill_n(d, cols, 0.f);
      return;
    }
    const std::int64_t lo = std::clamp<std::int64_t>(-dx - x0, 0, cols), hi = std::clamp<std::int64_t>(W - dx - x0, lo, cols);
    const float* src = plane + ys * W + x0 + dx;
    // Plain loops: at most a tile's width (<= 64 floats), where a library call costs more than the copy.
    for (std::int64_t j = 0; j < lo; ++j) d[j] = 0.f;
    for (std::int64_t j = lo; j < hi; ++j) d[j] = src[j];
    for (std::int64_t j = hi; j < cols; ++j) d[j] = 0.f;
  }

  // Panels of columns [p0, p0 + cols); step by step across all of them, so each step reads
  // one stretch of an image row (whole cache lines, in order).
  void operator()(std::int64_t p0, std::int64_t cols, std::int64_t s0, std::int64_t steps, gemm::Word* dst) const {
    auto* out = reinterpret_cast<float*>(dst);
    const std::int64_t panels = (cols + nr - 1) / nr;
    if (k == 1) {
      for (std::int64_t j = 0; j < panels; ++j)
        gemm::pack_rows(in + p0 + j * nr, H * W, std::min(nr, cols - j * nr), nr, s0, steps, dst + j * nr * steps);
      return;
    }
    const std::int64_t pad = k / 2;
    std::int64_t c = s0 / (k * k), dy = (s0 / k) % k - pad, dx = s0 % k - pad;
    for (std::int64_t s = 0; s < steps; ++s) {
      const float* plane = in + c * H * W;
      for (std::int64_t j = 0; j < panels; ++j) {
        const std::int64_t q0 = p0 + j * nr, n = std::min(nr, cols - j * nr);
        float* d = out + (j * steps + s) * nr;
        for (std::int64_t i = 0; i < n;) {  // runs of pixels within an image row
          const std::int64_t p = q0 + i, run = std::min(n - i, W - p % W);
          copy_shifted(plane, p / W + dy, p % W, dx, run, d + i);
          i += run;
        }
        for (std::int64_t i = n; i < nr; ++i) d[i] = 0.f;
      }
      if (++dx > pad) {  // next (c, dy, dx)
        dx = -pad;
        if (++dy > pad) dy = -pad, ++c;
      }
    }
  }
};

// Bias per output channel (row) and activation on a finished tile of the output (rows × cols).
template <class Act>
struct ConvTileEpilogue {
  float* out;
  std::int64_t HW;
  const float* bias;
  Act act;
  void operator()(std::int64_t m0, std::int64_t rows, std::int64_t n0, std::int64_t cols) const {
    using simd::Batch;
    for (std::int64_t r = 0; r < rows; ++r) {
      const Batch b(bias ? bias[m0 + r] : 0.f);
      float* row = out + (m0 + r) * HW + n0;
      simd::map(cols, row, [&](const Batch& v) { return act(v + b); }, row);
    }
  }
};
struct Relu {
  simd::Batch operator()(const simd::Batch& v) const { return xsimd::max(v, simd::Batch(0.f)); }
};

// Packs rows of the weights (cout × K, float32 or bf16 widened while packing: no float copy of
// bf16 weights) as A panels of a float32 kernel family.
template <class Wt>
struct PackConvWeights {
  const gemm::KernelFamily& f;
  const Wt* w;
  std::int64_t K;
  void operator()(std::int64_t m0, std::int64_t rows, std::int64_t s0, std::int64_t steps, gemm::Word* dst) const {
#if defined(EPONA_GEMM_X86)
    if (f.avx512_packing) {
      if constexpr (std::is_same_v<Wt, float>) return gemm::pack_f32_avx512(w + m0 * K, K, rows, f.mr, s0, steps, dst);
      else return gemm::pack_bf16_widened_avx512(w + m0 * K, K, rows, f.mr, s0, steps, dst);
    }
#endif
    gemm::pack_transposed(w + m0 * K, K, rows, f.mr, s0, steps, dst, gemm::FloatStep{});
  }
};

// One group of one image through the packed micro-kernels: out[cout × HW] = W[cout × K] · im2col.
template <class Wt>
void conv_group_packed(const gemm::KernelFamily& f, const float* in, std::int64_t cin, std::int64_t H,
                       std::int64_t W, std::int64_t k, const Wt* w, const float* bias, std::int64_t cout,
                       float* out, ConvAct act, int threads) {
  const std::int64_t K = cin * k * k, HW = H * W;
  const PackConvWeights<Wt> pack_w{f, w, K};  // the weights are the left operand's rows
  const PackIm2col pack_in{in, H, W, k, f.nr};
  const auto run = [&](auto act_fn) {
    gemm::run_gemm(f, cout, HW, K, threads, pack_w, pack_in, out, HW, ConvTileEpilogue<decltype(act_fn)>{out, HW, bias, act_fn});
  };
  switch (act) {
    case ConvAct::None: return run(detail::Identity{});
    case ConvAct::Relu: return run(Relu{});
    case ConvAct::Silu: return run(act::Silu{});
  }
}

// One image by Winograd F(2x2, 3x3) (conv_winograd.hpp), the activation fused into its output transform.
template <class W>
void conv3x3_winograd(const gemm::KernelFamily& f, int threads, const float* in, const W* w, const float* bias,
                      float* out, const Conv2dShape& s, ConvAct act) {
  const auto run = [&](auto act_fn) {
    winograd::conv3x3(f, threads, in, s.in_channels, s.height, s.width, w, bias, s.out_channels, out, act_fn);
  };
  switch (act) {
    case ConvAct::None: return run(detail::Identity{});
    case ConvAct::Relu: return run(Relu{});
    case ConvAct::Silu: return run(act::Silu{});
  }
}

// Depthwise (one input channel per output channel): direct shifted multiply-adds per plane.
inline void conv_depthwise(const float* in, std::int64_t planes, std::int64_t channels, std::int64_t H,
                           std::int64_t W, std::int64_t k, const float* w, const float* bias, float* out) {
  const std::int64_t pad = k / 2;
#pragma omp parallel for
  for (std::int64_t p = 0; p < planes; ++p) {
    const std::int64_t c = p % channels;
    const float* src = in + p * H * W;
    float* dst = out + p * H * W;
    const float* wc = w + c * k * k;
    std::fill_n(dst, H * W, bias ? bias[c] : 0.f);
    for (std::int64_t y = 0; y < H; ++y)
      for (std::int64_t dy = 0; dy < k; ++dy) {
        const std::int64_t ys = y + dy - pad;
        if (ys < 0 || ys >= H) continue;
        for (std::int64_t dx = 0; dx < k; ++dx) {
          const float wt = wc[dy * k + dx];
          const std::int64_t off = dx - pad;
          const std::int64_t x_lo = std::max<std::int64_t>(0, -off), x_hi = std::min(W, W - off);
          const float* s = src + ys * W + off;
          float* d = dst + y * W;
          for (std::int64_t x = x_lo; x < x_hi; ++x) d[x] += wt * s[x];
        }
      }
  }
}
}  // namespace conv_detail

// y = act(conv(x) + bias), x (N, C, H, W), y (N, O, H, W) preallocated (must not alias x).
// W: float or bf16 weights; activations and accumulation are float32. Threads: ctx.threads().
// 3x3 convolutions with one group and enough channels run Winograd F(2x2, 3x3)
// (conv_winograd.hpp; EPONA_CPU_CONV=direct turns it off), other ones the im2col GEMM.
template <class W>
void conv2d(Context& ctx, const float* x, const W* weight, const float* bias, float* y, const Conv2dShape& s,
            ConvAct act = ConvAct::None) {
  check_conv2d_shape(s);
  const std::int64_t cin_g = s.in_channels / s.groups, cout_g = s.out_channels / s.groups;
  const std::int64_t HW = s.height * s.width, k = s.kernel;
  const gemm::KernelFamily* family = detail::kernel_family<float>(active_isa(), HW);
  if (family && k == 3 && s.groups == 1 && winograd::enabled() &&
      winograd::worthwhile(s.in_channels, s.out_channels, s.height, s.width)) {
    for (std::int64_t n = 0; n < s.batch; ++n)
      conv_detail::conv3x3_winograd(*family, ctx.threads(), x + n * s.in_channels * HW, weight, bias,
                                    y + n * s.out_channels * HW, s, act);
    return;
  }
  const bool depthwise = cin_g == 1 && cout_g == 1;
  if (family && !depthwise) {  // bf16 weights are widened while packing
    for (std::int64_t n = 0; n < s.batch; ++n)
      for (std::int64_t g = 0; g < s.groups; ++g)
        conv_detail::conv_group_packed(*family, x + (n * s.in_channels + g * cin_g) * HW, cin_g, s.height, s.width, k,
                                       weight + g * cout_g * cin_g * k * k, bias ? bias + g * cout_g : nullptr, cout_g,
                                       y + (n * s.out_channels + g * cout_g) * HW, act, ctx.threads());
    return;
  }
  std::vector<float> widened;
  const float* w = conv_detail::weights_as_float(weight, s.out_channels * cin_g * k * k, widened);
  if (depthwise) {
    conv_detail::conv_depthwise(x, s.batch * s.in_channels, s.in_channels, s.height, s.width, k, w, bias, y);
    apply_conv_act(ctx, y, s.batch * s.out_channels * HW, act);
    return;
  }
  for (std::int64_t n = 0; n < s.batch; ++n)
    for (std::int64_t g = 0; g < s.groups; ++g)
      conv_detail::conv_group(x + (n * s.in_channels + g * cin_g) * HW, cin_g, s.height, s.width, k,
                              w + g * cout_g * cin_g * k * k, bias ? bias + g * cout_g : nullptr, cout_g,
                              y + (n * s.out_channels + g * cout_g) * HW, act, ctx.threads());
}

// RMSNorm2d (the DC-AE's "trms2d"): per pixel over the C channels, no mean subtraction,
//   y[n,c,p] = x[n,c,p] · 1/sqrt(mean_c x² + eps) · weight[c] + bias[c].
// Sums of squares in float32 in channel order, as the reference Triton kernel. In place allowed.
inline void rms_norm_2d(Context&, const float* x, float* y, std::int64_t N, std::int64_t C, std::int64_t HW,
                        const float* weight, const float* bias, float eps) {
  constexpr std::int64_t block = 256;  // pixels per task, as the reference kernel's tile
  const std::int64_t blocks = (HW + block - 1) / block;
#pragma omp parallel for collapse(2)
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t b = 0; b < blocks; ++b) {
      const std::int64_t p0 = b * block, np = std::min(block, HW - p0);
      float r[block];
      std::fill_n(r, np, 0.f);
      const float* xn = x + n * C * HW + p0;
      for (std::int64_t c = 0; c < C; ++c)
        for (std::int64_t i = 0; i < np; ++i) r[i] += xn[c * HW + i] * xn[c * HW + i];
      for (std::int64_t i = 0; i < np; ++i) r[i] = 1.0f / std::sqrt(r[i] / static_cast<float>(C) + eps);
      float* yn = y + n * C * HW + p0;
      for (std::int64_t c = 0; c < C; ++c)
        for (std::int64_t i = 0; i < np; ++i) yn[c * HW + i] = (xn[c * HW + i] * r[i]) * weight[c] + bias[c];
    }
}

// BatchNorm2d in eval mode: y = (x - mean[c]) / sqrt(var[c] + eps) · weight[c] + bias[c]. In place allowed.
inline void batch_norm_2d(Context&, const float* x, float* y, std::int64_t N, std::int64_t C, std::int64_t HW,
                          const float* weight, const float* bias, const float* mean, const float* var, float eps) {
#pragma omp parallel for
  for (std::int64_t p = 0; p < N * C; ++p) {
    const std::int64_t c = p % C;
    const float inv = 1.0f / std::sqrt(var[c] + eps), w = weight[c], b = bias[c], m = mean[c];
    const float* s = x + p * HW;
    float* d = y + p * HW;
    for (std::int64_t i = 0; i < HW; ++i) d[i] = (s[i] - m) * inv * w + b;
  }
}

// out[r*out_stride + i] = value[r*in_stride + i] · act(gate[r*in_stride + i]) for i < width:
// GLUMBConv's `x * act(gate)` and SwiGLU's `silu(w1 x) * (w3 x)`.
inline void gated_act(Context&, const float* value, const float* gate, float* out, std::int64_t rows,
                      std::int64_t width, std::int64_t in_stride, std::int64_t out_stride, ConvAct act) {
#pragma omp parallel for collapse(2)
  for (std::int64_t r = 0; r < rows; ++r)
    for (std::int64_t i = 0; i < width; ++i) {
      out[r * out_stride + i] = value[r * in_stride + i] * conv_detail::activate(gate[r * in_stride + i], act);
    }
}

// LiteMLA's evaluation order is backend neutral (core/shapes.hpp); cpu::AttentionOrder names it.
using epona::AttentionOrder;

// LiteMLA's ReLU linear attention. qkv (N, heads·3·d, HW) holds, per head a, q in channels
// [3da, 3da+d), k in [3da+d, 3da+2d), v in [3da+2d, 3da+3d); out (N, heads·d, HW), head a in
// channels [da, da+d). With q, k ← ReLU(q, k) and S(m, n) = Σ_j k[j,m] q[j,n]:
//   out[i, n] = Σ_m v[i,m] S(m,n) / (Σ_m S(m,n) + eps).
// Like the reference, HW > d evaluates ([v; 1] kᵀ) q (linear in HW), otherwise (v (kᵀ q)) with
// the column sums of kᵀ q (quadratic). ReLU is applied to q and k in place inside qkv.
inline void relu_linear_attention(Context& ctx, float* qkv, float* out, std::int64_t N, std::int64_t heads,
                                  std::int64_t d, std::int64_t HW, float eps,
                                  AttentionOrder order = AttentionOrder::Auto) {
  using conv_detail::RowMat;
  using Map = Eigen::Map<RowMat>;
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t a = 0; a < heads; ++a) {
      float* q = qkv + (n * heads * 3 + 3 * a) * d * HW;
      apply_conv_act(ctx, q, 2 * d * HW, ConvAct::Relu);  // q and k are adjacent
    }
  const bool linear = order == AttentionOrder::Auto ? HW > d : order == AttentionOrder::Linear;
#pragma omp parallel for collapse(2)
  for (std::int64_t n = 0; n < N; ++n)
    for (std::int64_t a = 0; a < heads; ++a) {
      const float* base = qkv + (n * heads * 3 + 3 * a) * d * HW;
      const Map Q(const_cast<float*>(base), d, HW), K(const_cast<float*>(base + d * HW), d, HW),
          V(const_cast<float*>(base + 2 * d * HW), d, HW);
      Map O(out + (n * heads + a) * d * HW, d, HW);
      if (linear) {
        const RowMat vk = V * K.transpose();                                         // (d, d)
        const Eigen::RowVectorXf ksum = K.rowwise().sum().transpose();               // the ones row
        const Eigen::RowVectorXf den = (ksum * Q).array() + eps;                     // (1, HW)
        O.noalias() = vk * Q;
        O.array().rowwise() /= den.array();
      } else {
        RowMat att = K.transpose() * Q;                                              // (HW, HW) [m, n]
        const Eigen::RowVectorXf den = att.colwise().sum().array() + eps;
        att.array().rowwise() /= den.array();
        O.noalias() = V * att;
      }
    }
}

}  // namespace epona::cpu
