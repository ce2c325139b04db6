// bench_gpu_dcae: the DC-AE f32c32 at its real widths and depths (DcaeConfig{}, random weights
// from nn::Bindable::randomize) on one GPU: decode (temporal blocks + decoder) and encode of
// one 512x1024 frame, bf16 and float32, with the cuDNN and the GEMM convolution engines; plus
// the largest single convolutions. Median of CUDA-event timings after warm-up; peak memory =
// weights + the scratch pool's high-water mark + inputs/outputs. One JSON object per line:
//   {"name": "dcae_decode", "dtype": "bf16", "engine": "auto", "ms": ..., "tflops": ..., ...}
// Options: --reps N (timed repetitions, default 20; float32 uses N/4), --hw H,W, --quick (the
// default-engine passes only), --stages (with --quick: also the bf16 decode broken into pieces),
// --layers (the first block of each decoder stage and the resampling steps taken apart),
// --no-f32 (bf16 passes only).
// EPONA_CUDA_CONV_FUSE=0 runs the unfused path (no BatchNorm folding, bias/ReLU/residual passes
// after each cuDNN conv), EPONA_CUDA_DCAE_FUSE=0 the unfused temporal blocks and upsampling
// pairs, EPONA_CUDA_CONV_TUNE=0 cuDNN for every bf16 3x3 conv (no measured choice), for
// side-by-side timing.
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <random>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"
#include "epona/model/dcae.hpp"
#include "gpu_event_timer.cuh"

using namespace epona;

namespace {

struct Options {
  int reps = 20;
  std::int64_t height = 512, width = 1024;
  bool quick = false, stages = false, layers = false, f32 = true;
};

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--reps" && i + 1 < argc) {
      o.reps = std::max(1, std::atoi(argv[++i]));
    } else if (a == "--hw" && i + 1 < argc) {
      long long h = 0, w = 0;
      EPONA_CHECK(std::sscanf(argv[++i], "%lld,%lld", &h, &w) == 2 && h % 32 == 0 && w % 32 == 0 && h > 0 && w > 0,
                  "--hw wants H,W, multiples of 32");
      o.height = h, o.width = w;
    } else if (a == "--quick") {
      o.quick = true;
    } else if (a == "--stages") {
      o.stages = true;
    } else if (a == "--layers") {
      o.layers = true;
    } else if (a == "--no-f32") {
      o.f32 = false;
    } else {
      fail("unknown option '", a, "' (--reps N, --hw H,W, --quick, --stages, --layers, --no-f32)");
    }
  }
  return o;
}

Tensor<float, Cuda> random_device(cuda::Context& ctx, Shape shape, std::uint32_t seed) {
  Tensor<float, Cpu> h(std::move(shape));
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  for (std::int64_t i = 0; i < h.numel(); ++i) h.data()[i] = u(gen);
  return cuda::to_device(ctx, h);
}

// Median milliseconds of `reps` runs of f (CUDA events on ctx's stream), after `warmup` runs.
double median_ms(cuda::Context& ctx, int warmup, int reps, const std::function<void()>& f) {
  std::vector<double> ms = bench::event_times_ms(ctx, reps, warmup, f);
  std::sort(ms.begin(), ms.end());
  return ms[ms.size() / 2];
}

const char* engine_name(cuda::ConvEngine e) {
  return e == cuda::ConvEngine::Gemm ? "gemm" : e == cuda::ConvEngine::Cudnn ? "cudnn" : "auto";
}

// Bytes of every parameter of a module.
struct ByteCounter {
  double bytes = 0;
  template <class T, class B>
  void param(const std::string&, Tensor<T, B>& t, const Shape&) {
    bytes += double(t.nbytes());
  }
  void counter(const std::string&) {}
};

void line(const char* name, const char* dtype, const char* engine, double ms, double gflop, double peak_mib,
          int reps, const std::string& extra = "") {
  std::printf("{\"name\": \"%s\", \"dtype\": \"%s\", \"engine\": \"%s\", \"ms\": %.3f, \"tflops\": %.1f, "
              "\"gflop\": %.1f, \"peak_mib\": %.0f, \"reps\": %d%s}\n",
              name, dtype, engine, ms, gflop / ms, gflop, peak_mib, reps, extra.c_str());
  std::fflush(stdout);
}

template <class T>
void bench_model(cuda::Context& ctx, const Options& o, const char* dtype) {
  DcaeConfig cfg;
  cfg.image_h = o.height, cfg.image_w = o.width;
  Dcae<Cuda, T> model(cfg);
  model.randomize(1);
  ByteCounter weights;
  model.visit_params("", weights);
  const DcaeFlops flops = dcae_flops(cfg, o.height, o.width, 1);
  const auto latents = random_device(ctx, {1, cfg.latent_channels, o.height / 32, o.width / 32}, 2);
  const auto images = random_device(ctx, {1, 3, o.height, o.width}, 3);
  const bool fp32 = std::is_same_v<T, float>;
  const int reps = fp32 ? std::max(3, o.reps / 4) : o.reps;
  const std::string cudnn = cuda::cudnn_unavailable(ctx);
  struct Variant {
    cuda::ConvEngine engine;
    bool graphs;
  };
  std::vector<Variant> variants{{cuda::ConvEngine::Auto, true}};
  if (!o.quick) {
    variants.push_back({cuda::ConvEngine::Auto, false});
    if (cudnn.empty()) variants.push_back({cuda::ConvEngine::Cudnn, true});
    if (!fp32) variants.push_back({cuda::ConvEngine::Gemm, true});  // float32 Auto already is the GEMM engine
  }
  for (const auto& v : variants) {
    ctx.policy().conv_engine = v.engine;
    model.use_graphs = v.graphs;
    const char* eng = v.engine != cuda::ConvEngine::Auto ? engine_name(v.engine)
                      : fp32 || !cudnn.empty()          ? "auto(gemm)"
                                                        : "auto(cudnn3x3+cublaslt1x1)";
    const auto peak_of = [&](const std::function<void()>& f, double io_bytes) {
      ctx.synchronize();
      cuda::reset_scratch_peak(ctx);
      f();
      ctx.synchronize();
      const double scratch = double(std::max<std::uint64_t>(cuda::scratch_usage(ctx).peak, cuda::graph_memory_peak(ctx)));
      return (weights.bytes + scratch + io_bytes) / (1024.0 * 1024.0);
    };
    Tensor<float, Cuda> out;
    const auto decode = [&] { out = model.decode(ctx, latents, false); };
    const auto encode = [&] { out = model.encode(ctx, images); };
    // staged copies of input and output when graphs replay, plus the caller's input and result
    const double io = double(latents.nbytes() + images.nbytes()) * (v.graphs ? 2 : 1);
    cuda::reset_conv_counts();
    const double dec_ms = median_ms(ctx, 3, reps, decode);
    const auto counts = cuda::conv_counts();
    const double dec_peak = peak_of(decode, io);
    char extra[260];
    std::snprintf(extra, sizeof extra,
                  ", \"graph\": %s, \"fusion\": %s, \"convs_eager_first_3\": {\"cudnn\": %lld, \"fused\": %lld, "
                  "\"gemm\": %lld, \"depthwise\": %lld}",
                  v.graphs ? "true" : "false", ctx.policy().conv_fusion ? "true" : "false", (long long)counts.cudnn,
                  (long long)counts.fused, (long long)counts.gemm, (long long)counts.depthwise);
    line("dcae_decode", dtype, eng, dec_ms, flops.decode_total() * 1e-9, dec_peak, reps, extra);
    const double enc_ms = median_ms(ctx, 3, reps, encode);
    const double enc_peak = peak_of(encode, io);
    std::snprintf(extra, sizeof extra, ", \"graph\": %s, \"fusion\": %s", v.graphs ? "true" : "false",
                  ctx.policy().conv_fusion ? "true" : "false");
    line("dcae_encode", dtype, eng, enc_ms, flops.encode * 1e-9, enc_peak, reps, extra);
  }
  model.use_graphs = true;
  ctx.policy().conv_engine = cuda::ConvEngine::Auto;
}

// Where decode time goes: the decoder's pieces timed one by one (median each), in bf16 with
// the default engine, on the maps they see in a real decode.
template <class T>
void bench_decoder_stages(cuda::Context& ctx, const Options& o, const char* dtype) {
  DcaeConfig cfg;
  cfg.image_h = o.height, cfg.image_w = o.width;
  Dcae<Cuda, T> model(cfg);
  model.randomize(1);
  using Map = typename Dcae<Cuda, T>::Map;
  const auto latents = random_device(ctx, {1, cfg.latent_channels, o.height / 32, o.width / 32}, 2);
  const auto& dec = model.decoder;
  const DcaeObserver<Cuda> none;
  const int reps = 10;
  Map z = nn::map_from_nchw<T>(ctx, latents);
  {
    const double ms = median_ms(ctx, 2, reps, [&] { (void)model.temporal.forward(ctx, z, 1); });
    line("decode_part_temporal", dtype, "auto", ms, dcae_flops(cfg, o.height, o.width, 1).temporal * 1e-9, 0, reps);
  }
  Map x;
  const double pin = median_ms(ctx, 2, reps, [&] {
    x = dec.project_in.forward(ctx, z);
    nn::add_channel_duplicate_up(ctx, z, x, 1);
  });
  line("decode_part_project_in", dtype, "auto", pin, 0, 0, reps);
  for (std::size_t s = dec.stages.size(); s-- > 1;) {
    const std::string id = std::to_string(s);
    if (dec.upsample[s].conv.out_channels > 0) {
      Map up;
      const double ms = median_ms(ctx, 2, reps, [&] { up = dec.upsample[s].forward(ctx, x); });
      const auto& c = dec.upsample[s].conv;
      const nn::MapDims d = nn::map_dims(x, "bench");
      const double gflop = 2.0 * 9 * c.in_channels * c.out_channels * double(d.pixels()) * 1e-9;
      line(("decode_part_stage" + id + "_upsample").c_str(), dtype, "auto", ms, gflop, 0, reps);
      x = up;
    }
    Map y = nn::copy_of(ctx, x);
    const double ms = median_ms(ctx, 2, reps, [&] { dec.stages[s].forward_inplace(ctx, y); });
    line(("decode_part_stage" + id + "_blocks").c_str(), dtype, "auto", ms, 0, 0, reps);
    dec.stages[s].forward_inplace(ctx, x);
  }
  Map img;
  const double pout = median_ms(ctx, 2, reps, [&] {
    Map t = nn::copy_of(ctx, x);
    dec.out_norm.forward_inplace(ctx, t, dec.out_act);
    img = dec.project_out.forward(ctx, t);
  });
  line("decode_part_project_out", dtype, "auto", pout, 0, 0, reps);
  Tensor<float, Cuda> out;
  const double conv_ms = median_ms(ctx, 2, reps, [&] { out = nn::map_to_nchw(ctx, img); });
  line("decode_part_to_nchw_float", dtype, "auto", conv_ms, 0, 0, reps);
}

// Finer than the stages: the first block of each decoder stage taken apart (LiteMLA and GLUMBConv
// of an EViT block, one ResBlock), the upsampling pair's conv and its shuffle + shortcut, and
// project_out's norm, conv and shuffle; each piece alone, eagerly, median of 10.
template <class T>
void bench_decoder_layers(cuda::Context& ctx, const Options& o, const char* dtype) {
  DcaeConfig cfg;
  cfg.image_h = o.height, cfg.image_w = o.width;
  Dcae<Cuda, T> model(cfg);
  model.randomize(1);
  using Map = typename Dcae<Cuda, T>::Map;
  const auto& dec = model.decoder;
  const int reps = 10;
  const auto piece = [&](const std::string& name, const std::function<void()>& f) {
    line(("layer_" + name).c_str(), dtype, "auto", median_ms(ctx, 2, reps, f), 0, 0, reps);
  };
  const auto latents = random_device(ctx, {1, cfg.latent_channels, o.height / 32, o.width / 32}, 2);
  Map x = dec.project_in.forward(ctx, nn::map_from_nchw<T>(ctx, latents));
  for (std::size_t s = dec.stages.size(); s-- > 1;) {
    const std::string id = "stage" + std::to_string(s) + "_";
    if (dec.upsample[s].conv.out_channels > 0) {
      const auto& up = dec.upsample[s];
      Map conv_out = up.conv.forward(ctx, x);
      piece(id + "upsample_conv", [&] { (void)up.conv.forward(ctx, x); });
      piece(id + "upsample_shuffle_shortcut", [&] { (void)nn::pixel_shuffle_add_duplicate(ctx, conv_out, x, 2); });
      x = up.forward(ctx, x);
    }
    if (!dec.stages[s].blocks.empty()) {
      Map y = nn::copy_of(ctx, x);
      std::visit(
          [&](const auto& b) {
            using Block = std::decay_t<decltype(b)>;
            if constexpr (std::is_same_v<Block, nn::EfficientViTBlock<Cuda, T>>) {
              piece(id + "evit_litemla_branch", [&] { b.context.add_to(ctx, y); });
              piece(id + "evit_glumbconv_branch", [&] { b.local.add_to(ctx, y); });
              const nn::MapDims d = nn::map_dims(x, "bench");
              const Map qkv = b.context.qkv.forward(ctx, x);
              Map att = nn::new_map<T, Cuda>(ctx, d);
              piece(id + "evit_litemla_attention_only", [&] {
                cuda::relu_linear_attention(ctx, qkv.data(), att.data(), d.batch, b.context.heads(), b.context.head_dim,
                                            d.pixels(), b.context.eps);
              });
            } else {
              piece(id + "resblock", [&] { b.forward_inplace(ctx, y); });
            }
          },
          dec.stages[s].blocks.front());
    }
    dec.stages[s].forward_inplace(ctx, x);
  }
  Map t = nn::copy_of(ctx, x);
  piece("project_out_norm_relu", [&] { dec.out_norm.forward_inplace(ctx, t, dec.out_act); });
  Map conv_out = dec.project_out.conv.forward(ctx, t);
  piece("project_out_conv", [&] { (void)dec.project_out.conv.forward(ctx, t); });
  piece("project_out_shuffle", [&] { (void)nn::pixel_shuffle(ctx, conv_out, 2); });
  Map img = nn::pixel_shuffle(ctx, conv_out, 2);
  Tensor<float, Cuda> out({1, 3, o.height, o.width});
  piece("to_nchw_float", [&] { nn::map_to_nchw(ctx, img, out); });
}

// The largest convolutions of the decoder, alone: 3x3 at full width on the biggest maps.
template <class T>
void bench_convs(cuda::Context& ctx, const Options& o, const char* dtype) {
  struct Conv {
    const char* name;
    std::int64_t C, H, W, O, k;
  };
  const std::int64_t h = o.height, w = o.width;
  // decoder stage 1 (256 ch at H/2), stage 2 (512 ch at H/4), the upsample into stage 1
  // (512 -> 4·256 at H/4), and stage 3's 1x1 convs (512 ch at H/8: LiteMLA qkv, GLU expansion)
  const Conv convs[] = {{"conv3x3_stage1_256", 256, h / 2, w / 2, 256, 3},
                        {"conv3x3_stage2_512", 512, h / 4, w / 4, 512, 3},
                        {"conv3x3_up1_512to1024", 512, h / 4, w / 4, 1024, 3},
                        {"conv1x1_stage3_qkv_512to1536", 512, h / 8, w / 8, 1536, 1},
                        {"conv1x1_stage3_expand_512to4096", 512, h / 8, w / 8, 4096, 1},
                        {"conv1x1_stage3_point_2048to512", 2048, h / 8, w / 8, 512, 1},
                        {"conv_depthwise3x3_stage3_4096", 4096, h / 8, w / 8, 4096, 3}};
  for (const Conv& c : convs) {
    const bool depthwise = c.C == c.O && c.k == 3 && std::string(c.name).find("depthwise") != std::string::npos;
    const std::int64_t groups = depthwise ? c.C : 1;
    const Conv2dShape s{1, c.C, c.H, c.W, c.O, c.k, groups};
    Tensor<T, Cuda> x({1, c.H, c.W, c.C}), wt({c.O, c.k, c.k, c.C / groups}), b({c.O}), y({1, c.H, c.W, c.O});
    const auto fill = [&](auto& t, std::uint32_t seed) {
      Tensor<T, Cpu> hst(t.shape());
      std::mt19937 gen(seed);
      std::uniform_real_distribution<float> u(-1.f, 1.f);
      for (std::int64_t i = 0; i < hst.numel(); ++i) hst.data()[i] = T(u(gen));
      cuda::copy(ctx, t, hst);
    };
    fill(x, 1), fill(wt, 2), fill(b, 3);
    const double gflop = 2.0 * double(c.k * c.k) * double(c.C / groups) * double(c.O) * double(c.H) * double(c.W) * 1e-9;
    const double bytes = double(x.nbytes() + y.nbytes());
    for (const auto engine : {cuda::ConvEngine::Cudnn, cuda::ConvEngine::Gemm}) {
      if (engine == cuda::ConvEngine::Cudnn && !cuda::cudnn_unavailable(ctx).empty()) continue;
      if (depthwise && engine == cuda::ConvEngine::Gemm) continue;  // one kernel either way
      ctx.policy().conv_engine = engine;
      const double ms = median_ms(ctx, 3, 20, [&] { cuda::conv2d(ctx, x.data(), wt.data(), b.data(), y.data(), s, ConvAct::Relu); });
      char extra[64];
      std::snprintf(extra, sizeof extra, ", \"gb_per_s\": %.0f", bytes / (ms * 1e-3) * 1e-9);
      line(c.name, dtype, depthwise ? "own" : engine_name(engine), ms, gflop, 0, 20, extra);
    }
  }
  ctx.policy().conv_engine = cuda::ConvEngine::Auto;
}

// The memory-bound passes of the biggest maps: GB/s (bytes read + written).
template <class T>
void bench_elementwise(cuda::Context& ctx, const Options& o, const char* dtype) {
  const std::int64_t H = o.height / 2, W = o.width / 2, C = 256, P = H * W;  // decoder stage 1
  Tensor<T, Cuda> a({P, C}), b({P, C}), up({P / 4, 4 * C}), wide({P / 16, 4096});  // wide: stage 3's 8C map
  Tensor<float, Cuda> wt({C}), bs({C}), mean({C}), var({C});
  for (auto* t : {&a, &b}) cuda::fill_bytes(ctx, *t, 0x3c);
  for (auto* t : {&wt, &bs, &mean, &var}) cuda::fill_bytes(ctx, *t, 0x3f);
  cuda::fill_bytes(ctx, up, 0x3c);
  cuda::fill_bytes(ctx, wide, 0x3c);
  const double map = double(a.nbytes());
  const auto report = [&](const char* name, double bytes, const std::function<void()>& f) {
    const double ms = median_ms(ctx, 3, 20, f);
    char extra[64];
    std::snprintf(extra, sizeof extra, ", \"gb_per_s\": %.0f", bytes / (ms * 1e-3) * 1e-9);
    line(name, dtype, "own", ms, 0, 0, 20, extra);
  };
  report("norm_2d_add_bn_stage1", 3 * map, [&] {
    cuda::norm_2d_add(ctx, a.data(), b.data(), P, C, wt.data(), bs.data(), mean.data(), var.data(), 1e-5f);
  });
  report("rms_norm_2d_stage1", 2 * map, [&] { cuda::rms_norm_2d(ctx, a.data(), a.data(), 1, C, P, wt.data(), bs.data(), 1e-5f); });
  report("apply_relu_stage1", 2 * map, [&] { cuda::apply_conv_act(ctx, a.data(), a.numel(), ConvAct::Relu); });
  report("pixel_shuffle_into_stage1", 2 * map, [&] {
    cuda::pixel_shuffle_duplicate(ctx, up.data(), b.data(), ShuffleShape{1, 4 * C, H / 2, W / 2, 2}, C, false);
  });
  report("duplicate_shortcut_add_stage1", 2.5 * map, [&] {
    cuda::pixel_shuffle_duplicate(ctx, up.data(), b.data(), ShuffleShape{1, 2 * C, H / 2, W / 2, 2}, C, true);
  });
  report("gated_silu_stage3_4096to2048", 1.5 * double(wide.nbytes()), [&] {
    cuda::gated_act(ctx, wide.data(), wide.data() + 2048, a.data(), P / 16, 2048, 4096, 2048, ConvAct::Silu);
  });
  // stage 3's qkv (8192 pixels x 1536, read once) -> 8192 x 512
  report("lite_mla_stage3_16heads", double(P / 16) * (1536 + 512) * sizeof(T), [&] {
    cuda::relu_linear_attention(ctx, wide.data(), a.data(), 1, 16, 32, P / 16, 1e-15f);
  });
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Options o = parse(argc, argv);
    if (!cuda::has_gpu()) {
      std::printf("no CUDA device: nothing to measure\n");
      return 0;
    }
    cuda::Context ctx;
    const std::string cudnn = cuda::cudnn_unavailable(ctx);
    std::printf("# %s, %d SMs; DC-AE f32c32 at %lldx%lld; cuDNN: %s\n", ctx.info().name.c_str(),
                ctx.info().multiprocessors, (long long)o.height, (long long)o.width,
                cudnn.empty() ? "available" : cudnn.c_str());
    std::printf("# fused conv epilogues + BatchNorm folding: %s\n", ctx.policy().conv_fusion ? "on" : "off (EPONA_CUDA_CONV_FUSE=0)");
    bench_model<bf16>(ctx, o, "bf16");
    if (!o.quick || o.stages) bench_decoder_stages<bf16>(ctx, o, "bf16");
    if (o.layers) bench_decoder_layers<bf16>(ctx, o, "bf16");
    if (!o.quick) bench_convs<bf16>(ctx, o, "bf16");
    if (o.f32) bench_model<float>(ctx, o, "f32");
    if (!o.quick) bench_elementwise<bf16>(ctx, o, "bf16");
    const std::string refused = cuda::conv_fusion_report();
    std::printf("# cuDNN fused form refused: %s\n", refused.empty() ? "nowhere" : refused.c_str());
    const std::string tuned = cuda::conv_tuning_report();
    std::printf("# convs measured faster on the GEMM engine (Auto): %s\n", tuned.empty() ? "none" : tuned.c_str());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_gpu_dcae: %s\n", e.what());
    return 1;
  }
}
