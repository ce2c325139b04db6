// epona/cuda/conv/conv.cuh — the DC-AE's convolutions on the GPU over channels-last (NHWC) maps, as
// the CPU's cpu/conv.hpp: conv2d (cuDNN implicit GEMM, or our GEMM engine: im2col panel +
// cuBLASLt; depthwise as a direct kernel), bias + ReLU/SiLU epilogues, a residual-adding conv
// (conv2d_residual), and the GLU gate. With cuDNN, bias, ReLU and the residual add ride on the
// convolution's epilogue (its fused form); under Auto, small bf16 maps go to whichever engine
// was measured faster for the geometry. float32 never uses TF32; bf16 stores bf16 and
// accumulates in float32.
#pragma once

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <map>
#include <mutex>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/core/env.hpp"
#include "epona/core/shapes.hpp"
#include "epona/cuda/pointwise/activation.cuh"
#include "epona/cuda/conv/conv_cudnn.cuh"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/runtime/event_timer.hpp"
#include "epona/cuda/gemm/gemm.cuh"
#include "epona/cuda/runtime/scratch.hpp"

namespace epona::cuda {

// Which implementation runs the dense convolutions: ctx.policy().conv_engine (ConvEngine,
// runtime/kernel_policy.hpp; EPONA_CUDA_CONV). The fused epilogues: ctx.policy().conv_fusion
// (EPONA_CUDA_CONV_FUSE=0 keeps the unfused path runnable for side-by-side timing and checks;
// the BatchNorm folding at bind time, before any context, follows the environment: conv_fold.cuh).

namespace conv_detail {

// Convolutions run per engine since the start (or the last reset): reports and tests.
struct EngineCounts {
  std::atomic<std::int64_t> cudnn{0}, gemm{0}, depthwise{0}, fused{0};  // fused: cuDNN calls with the epilogue inside
};
inline EngineCounts& counts() {
  static EngineCounts c;
  return c;
}

struct ReluOp {
  __device__ float operator()(float v) const { return v > 0.f ? v : 0.f; }
};

// Calls f(op) with the device functor of `act` (Identity for None).
template <class F>
void with_act(ConvAct act, F&& f) {
  switch (act) {
    case ConvAct::None: f(detail::Identity{}); return;
    case ConvAct::Relu: f(ReluOp{}); return;
    case ConvAct::Silu: f(detail::SiluOp{}); return;
  }
}

// y[p, o] = act(y[p, o] + bias[o]) over pixels x channels (bias may be null). The sum is rounded
// to T before the activation, as a biased conv's output would be.
template <class T>
void bias_act(Context& ctx, T* y, std::int64_t pixels, std::int64_t channels, const T* bias, ConvAct act) {
  if (!bias && act == ConvAct::None) return;
  with_act(act, [&](auto op) { detail::bias_activation(ctx, y, channels, pixels, channels, bias, op); });
}

// ---- depthwise: one thread per (channel pack, run of kRun pixels along a row); the pack's
// k·k weights stay in registers across the run (3x3 packs: read with 16-byte loads). Taps are
// summed in (ky, kx) order from the bias.
constexpr int kRun = 16;   // pixels per thread: the weights are loaded once per run
constexpr int kMaxTaps = 9;  // 3x3 kernels (kSmall) keep their weights in registers; others read them per tap

template <class T, class Op, int kVec, bool kSmall>
__global__ void depthwise_kernel(const T* __restrict__ x, const T* __restrict__ w, const T* __restrict__ bias,
                                 T* __restrict__ y, std::int64_t images, int H, int W, int C, int k, bool act, Op op) {
  const int packs = C / kVec, pad = k / 2, runs = (W + kRun - 1) / kRun, taps = k * k;
  const std::int64_t total = images * H * runs * packs;
  for (std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x; i < total;
       i += std::int64_t{gridDim.x} * blockDim.x) {
    const int c0 = static_cast<int>(i % packs) * kVec;
    const std::int64_t row_run = i / packs;
    const int x0 = static_cast<int>(row_run % runs) * kRun;
    const std::int64_t image_row = row_run / runs;  // n·H + y
    const int yo = static_cast<int>(image_row % H);
    const std::int64_t n = image_row / H;
    float wr[kSmall ? kMaxTaps : 1][kVec];
    if constexpr (kSmall && kVec == detail::kPack) {
      // the pack's 8 x 9 weights are 72 consecutive values (16-byte aligned): 9 vector loads
#pragma unroll
      for (int q = 0; q < kMaxTaps; ++q) {
        float part[detail::kPack];
        detail::load8(w + c0 * kMaxTaps + q * detail::kPack, part);
#pragma unroll
        for (int e = 0; e < detail::kPack; ++e) {
          const int flat = q * detail::kPack + e;  // = j·9 + tap
          wr[flat % kMaxTaps][flat / kMaxTaps] = part[e];
        }
      }
    } else if constexpr (kSmall) {
#pragma unroll
      for (int t = 0; t < kMaxTaps; ++t)
#pragma unroll
        for (int j = 0; j < kVec; ++j) wr[t][j] = detail::to_f32(w[(c0 + j) * taps + t]);
    }
    float b[kVec];
#pragma unroll
    for (int j = 0; j < kVec; ++j) b[j] = bias ? detail::to_f32(bias[c0 + j]) : 0.f;
    const int x_end = min(W, x0 + kRun);
    for (int xo = x0; xo < x_end; ++xo) {
      float acc[kVec];
#pragma unroll
      for (int j = 0; j < kVec; ++j) acc[j] = b[j];
      // acc += w(tap) · x(ys, xs) for one in-image tap
      const auto add_tap = [&](int ys, int xs, int tap) {
        const T* src = x + ((n * H + ys) * W + xs) * C + c0;
        float v[kVec];
        if constexpr (kVec == detail::kPack) {
          detail::load8(src, v);
        } else {
          v[0] = detail::to_f32(src[0]);
        }
#pragma unroll
        for (int j = 0; j < kVec; ++j) {
          if constexpr (kSmall)
            acc[j] += wr[tap][j] * v[j];
          else
            acc[j] += detail::to_f32(w[(c0 + j) * taps + tap]) * v[j];
        }
      };
      if constexpr (kSmall) {  // 3x3: taps unrolled, weights indexed by constants
#pragma unroll
        for (int ky = 0; ky < 3; ++ky) {
          const int ys = yo + ky - 1;
          if (ys < 0 || ys >= H) continue;
#pragma unroll
          for (int kx = 0; kx < 3; ++kx) {
            const int xs = xo + kx - 1;
            if (xs >= 0 && xs < W) add_tap(ys, xs, ky * 3 + kx);
          }
        }
      } else {
        for (int ky = 0; ky < k; ++ky) {
          const int ys = yo + ky - pad;
          if (ys < 0 || ys >= H) continue;
          for (int kx = 0; kx < k; ++kx) {
            const int xs = xo + kx - pad;
            if (xs >= 0 && xs < W) add_tap(ys, xs, ky * k + kx);
          }
        }
      }
#pragma unroll
      for (int j = 0; j < kVec; ++j) acc[j] = act ? op(detail::round_to<T>(acc[j])) : acc[j];
      T* dst = y + ((n * H + yo) * W + xo) * C + c0;
      if constexpr (kVec == detail::kPack) {
        detail::store8(dst, acc);
      } else {
        dst[0] = detail::from_f32<T>(acc[0]);
      }
    }
  }
}

template <class T>
void depthwise(Context& ctx, const T* x, const T* w, const T* bias, T* y, const Conv2dShape& s, ConvAct act) {
  const std::int64_t C = s.in_channels;
  EPONA_CHECK(s.height <= 0x7fffffff && s.width <= 0x7fffffff && C <= 0x7fffffff && s.kernel <= 0x7fffffff,
              "depthwise conv2d: extents exceed int range");
  const bool packed = C % detail::kPack == 0 && detail::aligned16(x) && detail::aligned16(y) && detail::aligned16(w);
  const std::int64_t runs = (s.width + kRun - 1) / kRun;
  const std::int64_t items = s.batch * s.height * runs * (packed ? C / detail::kPack : C);
  if (items == 0) return;
  constexpr int threads = 128;
  const unsigned blocks = detail::grid_for(items, threads);
  const int H = static_cast<int>(s.height), W = static_cast<int>(s.width), k = static_cast<int>(s.kernel);
  const bool activate = act != ConvAct::None, small = k == 3;
  const auto launch = [&](auto op, auto vec, auto small_taps) {
    depthwise_kernel<T, decltype(op), decltype(vec)::value, decltype(small_taps)::value>
        <<<blocks, threads, 0, ctx.stream()>>>(x, w, bias, y, s.batch, H, W, static_cast<int>(C), k, activate, op);
  };
  using Pack = std::integral_constant<int, detail::kPack>;
  using One = std::integral_constant<int, 1>;
  conv_detail::with_act(act, [&](auto op) {
    if (packed && small) launch(op, Pack{}, std::true_type{});
    else if (packed) launch(op, Pack{}, std::false_type{});
    else if (small) launch(op, One{}, std::true_type{});
    else launch(op, One{}, std::false_type{});
    EPONA_CUDA_CHECK_LAUNCH();
  });
}

// value · round(act(gate)) over strided rows (gated_act's element-wise work).
template <class T, class Op>
struct GatedEach {
  const T *value, *gate;
  T* out;
  std::int64_t in_stride, out_stride;
  Op op;
  __device__ void pack(std::int64_t r, std::int64_t c) const {
    float a[detail::kPack], b[detail::kPack];
    detail::load8(value + r * in_stride + c, a);
    detail::load8(gate + r * in_stride + c, b);
#pragma unroll
    for (int i = 0; i < detail::kPack; ++i) a[i] *= detail::round_to<T>(op(b[i]));
    detail::store8(out + r * out_stride + c, a);
  }
  __device__ void one(std::int64_t r, std::int64_t c) const {
    const float g = detail::round_to<T>(op(detail::to_f32(gate[r * in_stride + c])));
    out[r * out_stride + c] = detail::from_f32<T>(detail::to_f32(value[r * in_stride + c]) * g);
  }
};

// residual = round(residual + round(y + bias)) over pixels x channels (the unfused tail of
// conv2d_residual: y is the conv's rounded output, the biased value is rounded as a biased
// conv's output would be).
template <class T>
struct BiasResidualEach {
  const T* y;
  const T* bias;  // may be null
  T* residual;
  std::int64_t channels;
  __device__ void pack(std::int64_t r, std::int64_t c) const {
    float a[detail::kPack], b[detail::kPack];
    detail::load8(y + r * channels + c, a);
    detail::load8(residual + r * channels + c, b);
#pragma unroll
    for (int i = 0; i < detail::kPack; ++i)
      b[i] += bias ? detail::round_to<T>(a[i] + detail::to_f32(bias[c + i])) : a[i];
    detail::store8(residual + r * channels + c, b);
  }
  __device__ void one(std::int64_t r, std::int64_t c) const {
    const float v = detail::to_f32(y[r * channels + c]);
    const float t = bias ? detail::round_to<T>(v + detail::to_f32(bias[c])) : v;
    residual[r * channels + c] = detail::from_f32<T>(detail::to_f32(residual[r * channels + c]) + t);
  }
};

// ---- GEMM engine: panel[r, (ky·k + kx)·cg + c] = x[pixel p0 + r shifted by (ky, kx), channel c0 + c]
// (zero outside the image), then y[p, o] = panel · w[o]ᵀ through cuBLASLt.
template <class T>
struct Im2colEach {
  const T* x;  // one image, (H, W, C)
  T* panel;    // (rows, k·k·cg)
  std::int64_t p0;
  int H, W, C, c0, cg, k;
  // column c of the panel row `r` (c in [0, k·k·cg)), 8 columns of one tap at a time when packed
  __device__ const T* source(std::int64_t r, std::int64_t col) const {
    const int tap = static_cast<int>(col / cg), c = static_cast<int>(col % cg);
    const std::int64_t p = p0 + r;
    const int ys = static_cast<int>(p / W) + tap / k - k / 2, xs = static_cast<int>(p % W) + tap % k - k / 2;
    if (ys < 0 || ys >= H || xs < 0 || xs >= W) return nullptr;
    return x + (std::int64_t{ys} * W + xs) * C + c0 + c;
  }
  __device__ void pack(std::int64_t r, std::int64_t col) const {
    const T* s = source(r, col);
    T* d = panel + r * (std::int64_t{k} * k * cg) + col;
    if (s) {
      *reinterpret_cast<uint4*>(d) = *reinterpret_cast<const uint4*>(s);
      if constexpr (sizeof(T) == 4) reinterpret_cast<uint4*>(d)[1] = reinterpret_cast<const uint4*>(s)[1];
    } else {
      *reinterpret_cast<uint4*>(d) = make_uint4(0, 0, 0, 0);
      if constexpr (sizeof(T) == 4) reinterpret_cast<uint4*>(d)[1] = make_uint4(0, 0, 0, 0);
    }
  }
  __device__ void one(std::int64_t r, std::int64_t col) const {
    const T* s = source(r, col);
    panel[r * (std::int64_t{k} * k * cg) + col] = s ? *s : detail::from_f32<T>(0.f);
  }
};

// Largest im2col panel (bytes): bounds the engine's scratch memory on big maps. Tests set a
// smaller ctx.policy().conv_panel_bytes (0 or less: this default).
inline constexpr std::int64_t kMaxPanelBytes = KernelPolicy::default_conv_panel_bytes;
inline std::int64_t panel_bytes(const Context& ctx) {
  const std::int64_t b = ctx.policy().conv_panel_bytes;
  return b > 0 ? b : kMaxPanelBytes;
}

template <class T>
void gemm_conv(Context& ctx, const T* x, const T* w, const T* bias, T* y, const Conv2dShape& s, ConvAct act) {
  const std::int64_t C = s.in_channels, O = s.out_channels, k = s.kernel, HW = s.height * s.width;
  const std::int64_t cg = C / s.groups, og = O / s.groups, K = k * k * cg;
  // SiLU rides on linear's epilogue (after its bias); ReLU runs as a pass after the product.
  const Epilogue epi = act == ConvAct::Silu ? Epilogue::Silu : Epilogue::None;
  const auto product = [&](const T* a, std::int64_t lda, std::int64_t rows, std::int64_t g, T* out) {
    linear(ctx, a, lda, w + g * og * K, bias ? bias + g * og : nullptr, out + g * og, O, rows, og, K, epi);
  };
  if (k == 1) {
    for (std::int64_t g = 0; g < s.groups; ++g) product(x + g * cg, C, s.batch * HW, g, y);
  } else {
    const std::int64_t rows = std::clamp<std::int64_t>(panel_bytes(ctx) / (K * std::int64_t{sizeof(T)}), 1, HW);
    Tensor<T, Cuda> panel = scratch_tensor<T>(ctx, {rows, K});
    const bool packed = cg % detail::kPack == 0 && detail::aligned16(x) && detail::aligned16(panel.data());
    for (std::int64_t n = 0; n < s.batch; ++n)
      for (std::int64_t g = 0; g < s.groups; ++g)
        for (std::int64_t p0 = 0; p0 < HW; p0 += rows) {
          const std::int64_t r = std::min(rows, HW - p0);
          const Im2colEach<T> f{x + n * HW * C, panel.data(), p0, static_cast<int>(s.height),
                                static_cast<int>(s.width), static_cast<int>(C), static_cast<int>(g * cg),
                                static_cast<int>(cg), static_cast<int>(k)};
          detail::for_each(ctx, r, K, packed, f);
          product(panel.data(), K, r, g, y + (n * HW + p0) * O);
        }
  }
  if (act == ConvAct::Relu) detail::map(ctx, y, y, s.batch * HW * O, ReluOp{});
}

}  // namespace conv_detail

// Why cuDNN does not run on ctx's device ("" when it does).
inline std::string cudnn_unavailable(Context& ctx) { return cudnn::Engine::get().unavailable(ctx); }
// What a recorded graph of convolutions depends on beyond its buffers and sizes: ctx's engine,
// fusion and the GEMM engine's panel budget (model code keys its graphs with it).
inline std::uint64_t graph_variant(const Context& ctx) {
  return static_cast<std::uint64_t>(ctx.policy().conv_engine) | (ctx.policy().conv_fusion ? 16u : 0u) |
         (static_cast<std::uint64_t>(conv_detail::panel_bytes(ctx)) << 8);
}
// Geometries where cuDNN refused the fused form so far, with its reasons ("" when none).
inline std::string conv_fusion_report() { return cudnn::Engine::get().fused_report(); }
// Destroys the cuDNN handles and plans (they are made again on the next convolution): frees
// cuDNN's memory before a program's CUDA teardown.
inline void release_cudnn() { cudnn::Engine::get().release(); }

struct ConvCounts {
  std::int64_t cudnn = 0, gemm = 0, depthwise = 0, fused = 0;  // fused: of the cuDNN ones
};
inline ConvCounts conv_counts() {
  auto& c = conv_detail::counts();
  return {c.cudnn.load(), c.gemm.load(), c.depthwise.load(), c.fused.load()};
}
inline void reset_conv_counts() {
  auto& c = conv_detail::counts();
  c.cudnn = 0, c.gemm = 0, c.depthwise = 0, c.fused = 0;
}

// x += y-style activation in place: ReLU, SiLU or nothing.
template <class T>
void apply_conv_act(Context& ctx, T* x, std::int64_t n, ConvAct act) {
  static_assert(is_device_float<T>, "apply_conv_act takes float or bf16");
  if (act == ConvAct::None || n == 0) return;
  conv_detail::with_act(act, [&](auto op) { detail::map(ctx, x, x, n, op); });
}

namespace conv_detail {
// Whether the dense conv of shape s runs on cuDNN under the current engine setting (Auto: bf16
// k x k only); an explicit Cudnn request that cuDNN cannot serve is an error.
template <class T>
bool wants_cudnn(const Context& ctx, const Conv2dShape& s) {
  const ConvEngine engine = ctx.policy().conv_engine;
  return engine == ConvEngine::Cudnn || (engine == ConvEngine::Auto && s.kernel > 1 && !std::is_same_v<T, float>);
}
template <class T>
void require_cudnn(Context& ctx, const Conv2dShape& s) {
  EPONA_CHECK(ctx.policy().conv_engine != ConvEngine::Cudnn, "conv2d: the cuDNN engine was requested but cannot run ",
              s.in_channels, "->", s.out_channels, " k=", s.kernel, " at ", s.height, "x", s.width, ": ",
              cudnn::Engine::get().plan_problem<T>(ctx, s));
}
inline void check_conv_args(const void* x, const void* weight, const void* y, const Conv2dShape& s) {
  check_conv2d_shape(s);
  EPONA_CHECK(x && weight && y, "conv2d: null input, weight or output");
  EPONA_CHECK(s.height * s.width <= 0x7fffffff, "conv2d: ", s.height, "x", s.width, " exceeds one image's index range");
}

// ---- measured engine choice (Auto, bf16 k x k): cuDNN's kernels run well below their peak on
// small maps with many output channels (the decoder's upsampling convs at 16x32 .. 64x128:
// 240-350 TFLOP/s), where an im2col panel + cuBLASLt does better. Each such geometry (panel at
// most kTunePanelBytes) is timed once on both engines, eagerly (3 runs each, the best of each),
// and remembered; the GEMM engine is taken only when at least 10% faster, so that the choice
// does not flip on noise. Never during a graph recording (cuDNN is used then, undecided).
// ctx.policy().conv_tuning off (EPONA_CUDA_CONV_TUNE=0) turns it off (cuDNN for every bf16
// k x k conv, as before).
inline constexpr std::int64_t kTunePanelBytes = std::int64_t{128} << 20;
struct TuneState {
  std::mutex mutex;
  std::map<std::array<std::int64_t, 9>, bool> gemm_faster;  // (device, geometry, act, bias) -> choice
  std::string report;                                      // geometries sent to the GEMM engine
};
inline TuneState& tune_state() {
  static TuneState t;
  return t;
}

// The best (smallest) of `reps` event timings of f in ms (f enqueues work on ctx's stream).
template <class F>
float best_ms(Context& ctx, int reps, const F& f) {
  const std::vector<float> runs = event_times_ms(ctx, reps, f);
  return runs.empty() ? INFINITY : *std::min_element(runs.begin(), runs.end());
}

// Whether this Auto bf16 conv should run on the GEMM engine: decided on its first eager call
// (run_cudnn returns false when cuDNN cannot run it: then no, the caller falls back anyway).
template <class T, class CudnnRun, class GemmRun>
bool tuned_to_gemm(Context& ctx, const Conv2dShape& s, ConvAct act, bool has_bias, const CudnnRun& run_cudnn,
                   const GemmRun& run_gemm) {
  const KernelPolicy& policy = ctx.policy();
  if (std::is_same_v<T, float> || policy.conv_engine != ConvEngine::Auto || !policy.conv_tuning || s.groups != 1 ||
      s.batch * s.height * s.width * s.kernel * s.kernel * s.in_channels * std::int64_t{sizeof(T)} > kTunePanelBytes)
    return false;
  const std::array<std::int64_t, 9> key{ctx.info().device, s.batch, s.in_channels, s.height, s.width, s.out_channels,
                                        s.kernel, static_cast<std::int64_t>(act), has_bias ? 1 : 0};
  TuneState& t = tune_state();
  std::lock_guard<std::mutex> lock(t.mutex);
  if (const auto it = t.gemm_faster.find(key); it != t.gemm_faster.end()) return it->second;
  if (detail::capturing(ctx.stream())) return false;
  bool cudnn_ok = true;
  const float cudnn_ms = best_ms(ctx, 3, [&] { cudnn_ok = cudnn_ok && run_cudnn(); });
  const float gemm_ms = cudnn_ok ? best_ms(ctx, 3, run_gemm) : 0.f;
  const bool gemm = cudnn_ok && gemm_ms < 0.9f * cudnn_ms;
  t.gemm_faster.emplace(key, gemm);
  if (gemm)
    t.report += (t.report.empty() ? "" : "; ") + std::to_string(s.in_channels) + "->" +
                std::to_string(s.out_channels) + " k" + std::to_string(s.kernel) + " at " + std::to_string(s.height) +
                "x" + std::to_string(s.width) + ": " + std::to_string(gemm_ms) + " vs cuDNN " +
                std::to_string(cudnn_ms) + " ms";
  return gemm;
}
}  // namespace conv_detail

// The geometries the measured engine choice (small bf16 k x k convs under Auto, with
// ctx.policy().conv_tuning) sent to the GEMM engine so far, with both timings.
inline std::string conv_tuning_report() {
  auto& t = conv_detail::tune_state();
  std::lock_guard<std::mutex> lock(t.mutex);
  return t.report;
}

// y = act(conv(x) + bias): x (N, H, W, C) channels-last, weight [O, k, k, C/groups] (the
// channels-last layout of nn::conv_weight_layout), bias [O] or null, y (N, H, W, O), not
// aliasing x. Stride 1, zero padding k/2. Asynchronous on ctx's stream. On cuDNN, bias and ReLU
// run inside the convolution (one rounding of conv + bias, as the unfused path's round(round(conv)
// + bias) up to the inner rounding); SiLU stays a separate pass.
template <class T>
void conv2d(Context& ctx, const T* x, const T* weight, const T* bias, T* y, const Conv2dShape& s,
            ConvAct act = ConvAct::None) {
  static_assert(is_device_float<T>, "conv2d takes float or bf16");
  conv_detail::check_conv_args(x, weight, y, s);
  if (s.batch == 0) return;
  auto& counts = conv_detail::counts();
  if (s.in_channels == s.groups && s.out_channels == s.groups) {
    conv_detail::depthwise(ctx, x, weight, bias, y, s, act);
    ++counts.depthwise;
    return;
  }
  if (conv_detail::wants_cudnn<T>(ctx, s)) {
    auto& engine = cudnn::Engine::get();
    const auto run_cudnn = [&]() -> int {  // 2: fused call, 1: conv + epilogue pass, 0: cuDNN cannot
      if (ctx.policy().conv_fusion && bias && act != ConvAct::Silu &&
          engine.forward_fused(ctx, x, weight, bias, static_cast<const T*>(nullptr), y, s, act == ConvAct::Relu))
        return 2;
      if (!engine.forward(ctx, x, weight, y, s)) return 0;
      conv_detail::bias_act(ctx, y, s.batch * s.height * s.width, s.out_channels, bias, act);
      return 1;
    };
    const auto run_gemm = [&] { conv_detail::gemm_conv(ctx, x, weight, bias, y, s, act); };
    if (conv_detail::tuned_to_gemm<T>(ctx, s, act, bias != nullptr, [&] { return run_cudnn() > 0; }, run_gemm)) {
      run_gemm();
      ++counts.gemm;
      return;
    }
    if (const int done = run_cudnn()) {
      ++counts.cudnn;
      if (done == 2) ++counts.fused;
      return;
    }
    conv_detail::require_cudnn<T>(ctx, s);
  }
  conv_detail::gemm_conv(ctx, x, weight, bias, y, s, act);
  ++counts.gemm;
}

// residual += conv(x) + bias (no activation): the post-norm residual branch of a ResBlock whose
// eval-mode BatchNorm is folded into the conv (nn::fold_batch_norm). On cuDNN one fused call
// (the residual is the epilogue's z input, written in place, rounded once); otherwise the conv
// into scratch, then residual = round(residual + round(conv + bias)) in one pass.
template <class T>
void conv2d_residual(Context& ctx, const T* x, const T* weight, const T* bias, T* residual, const Conv2dShape& s) {
  static_assert(is_device_float<T>, "conv2d_residual takes float or bf16");
  conv_detail::check_conv_args(x, weight, residual, s);
  if (s.batch == 0) return;
  const bool dense = !(s.in_channels == s.groups && s.out_channels == s.groups);
  if (dense && ctx.policy().conv_fusion && conv_detail::wants_cudnn<T>(ctx, s) &&
      cudnn::Engine::get().forward_fused(ctx, x, weight, bias, residual, residual, s, false)) {
    auto& counts = conv_detail::counts();
    ++counts.cudnn, ++counts.fused;
    return;
  }
  const std::int64_t pixels = s.batch * s.height * s.width, O = s.out_channels;
  Tensor<T, Cuda> y = scratch_tensor<T>(ctx, {pixels, O});
  conv2d(ctx, x, weight, static_cast<const T*>(nullptr), y.data(), s);
  const bool packed = O % detail::kPack == 0 && detail::aligned16(y.data()) && detail::aligned16(residual);
  detail::for_each(ctx, pixels, O, packed, conv_detail::BiasResidualEach<T>{y.data(), bias, residual, O});
}

// out[r·out_stride + i] = value[r·in_stride + i] · act(gate[r·in_stride + i]) for i < width
// (GLUMBConv's x · act(gate), SwiGLU's silu(w1 x) · (w3 x)); act(gate) is rounded to T first,
// as the reference's separate activation. out may be gate (same index).
template <class T>
void gated_act(Context& ctx, const T* value, const T* gate, T* out, std::int64_t rows, std::int64_t width,
               std::int64_t in_stride, std::int64_t out_stride, ConvAct act) {
  static_assert(is_device_float<T>, "gated_act takes float or bf16");
  EPONA_CHECK(rows >= 0 && width >= 0 && in_stride >= width && out_stride >= width, "gated_act: bad extents (rows ",
              rows, ", width ", width, ", strides ", in_stride, ", ", out_stride, ")");
  const bool packed = detail::packable(value, width, in_stride) && detail::packable(gate, width, in_stride) &&
                      detail::packable(out, width, out_stride);
  conv_detail::with_act(act, [&](auto op) {
    detail::for_each(ctx, rows, width, packed,
                     conv_detail::GatedEach<T, decltype(op)>{value, gate, out, in_stride, out_stride, op});
  });
}

}  // namespace epona::cuda
