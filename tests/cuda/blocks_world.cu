// The world model's layers and blocks on the GPU against the CPU backend on random data and
// random weights (model/random_weights.hpp) at head dim 128 (the real one): the world-model
// kernels added for the GPU (copy, strided copy, float32 -> bf16 conversion, Euler update alone
// and fused with the conversion, qk_norm_rope's row path vs its head-per-warp path),
// the DiT blocks one by one (DoubleStreamBlock, SingleStreamBlock full and pruned, LastLayer),
// the MST block by block (observer), whole DiT evaluations and samples (batch 2: modulation
// tables, input conversion, recorded sampler graph) and world-model steps. Bounds: float32
// within 1e-5 (max |gpu - cpu| / max |cpu|, per block; 1e-4 after a 10-step sample, as the
// golden README for float32 ports); bf16 (bf16 weights and activations vs the float32 CPU)
// within twice the official bf16 recipe's error of the matching golden stage (manifest.json).
// Outputs and the arena are poisoned (0xFF: NaN) before every GPU call.
#include <doctest/doctest.h>

#include <array>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "../model/world_golden.hpp"
#include "cuda_test_util.cuh"
#include "epona/cuda/backend.cuh"
#include "epona/flow/schedule.hpp"
#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"

using namespace epona;

namespace {

// Small, but with the real head dim 128, several frames, and 32 image tokens.
WorldModelConfig small_config() {
  WorldModelConfig c;
  c.image_h = 128;
  c.image_w = 256;  // latent 4 x 8
  c.condition_frames = 3;
  c.n_embd = 256;
  c.n_head = 2;
  c.n_layer = {2, 2, 2};
  c.n_embd_dit = 256;
  c.n_head_dit = 2;
  c.axes_dim_dit = {16, 56, 56};
  c.n_layer_traj = {1, 1};
  c.n_embd_dit_traj = 256;
  c.n_head_dit_traj = 2;
  c.axes_dim_dit_traj = {16, 56, 56};
  c.num_sampling_steps = 10;
  return c;
}

const WorldModelConfig& config() {
  static const WorldModelConfig c = small_config();
  return c;
}
const io::TensorMap& weights() {
  static const io::TensorMap w = model::random_world_weights(config(), 11);
  return w;
}

cuda::Context& gpu() {
  static cuda::Context ctx;
  return ctx;
}
cpu::Context& cpu_ctx() {
  static cpu::Context ctx;
  return ctx;
}

double official_bf16_error(const std::string& name) {
  static const nlohmann::json manifest = [] {
    std::ifstream in(test::golden_dir() + "/manifest.json");
    return nlohmann::json::parse(in);
  }();
  return manifest.at("tolerance_official_bf16_recipe").at("official_recipe_vs_fp32_golden").at(name).at("rel_max").get<double>();
}

// The bound of a GPU result of weight type W against the float32 CPU: 1e-5 (float32, or
// `f32_bound` for composed runs) or twice the official bf16 recipe's error at `stage`.
template <class W>
double bound(const std::string& stage, double f32_bound = 1e-5) {
  return std::is_same_v<W, float> ? f32_bound : 2 * official_bf16_error(stage);
}

void expect_close(const std::string& what, const Tensor<float, Cpu>& gpu_out, const Tensor<float, Cpu>& cpu_out,
                  double limit) {
  REQUIRE(gpu_out.shape() == cpu_out.shape());
  const double rel = test::rel_max(gpu_out, cpu_out);
  MESSAGE(what, ": rel ", rel, " (limit ", limit, ")");
  CHECK(rel <= limit);
}

void poison_arena(Arena<Cuda>& arena) {
  arena.reset();
  auto all = arena.take<unsigned char>({static_cast<std::int64_t>(arena.capacity())});
  cuda::fill_bytes(gpu(), all, 0xFF);
  arena.reset();
}

template <class T>
Tensor<T, Cuda> upload(const Tensor<float, Cpu>& h) {
  return test::upload<T>(gpu(), h);
}
template <class T>
Tensor<float, Cpu> download(const Tensor<T, Cuda>& d) {
  return test::download(gpu(), d);
}

template <class Context>
using BackendOf_t = typename BackendOf<std::decay_t<Context>>::type;

template <class Block>
void bind(Block& block, const std::string& prefix) {
  io::BindReport report(weights());
  block.bind(weights(), prefix, report);
  report.finish(true, [&](const std::string& k) { return k.rfind(prefix, 0) != 0; });
}

}  // namespace

TEST_CASE("world-model kernels: copy, strided copy, conversion, Euler update (float32 and bf16 velocity, fused with the conversion)") {
  EPONA_REQUIRE_GPU();
  auto& ctx = gpu();
  const auto src = test::random_tensor({37, 53}, 1);
  auto dst = test::upload<float>(ctx, test::random_tensor({37, 53}, 2));
  cuda::copy(ctx, upload<float>(src).data(), dst.data(), src.numel());
  CHECK(test::rel_max(download(dst), src) == 0);
  // Strided: columns [5, 5 + 17) of 11 rows of src into columns [3, 20) of rows 64 apart.
  auto wide = upload<float>(test::random_tensor({11, 64}, 3));
  const auto before = download(wide);
  const auto dsrc = upload<float>(src);
  cuda::copy_rows(ctx, dsrc.data() + 5, 53, wide.data() + 3, 64, 11, 17);
  const auto after = download(wide);
  int wrong = 0;
  for (int r = 0; r < 11; ++r)
    for (int c = 0; c < 64; ++c)
      wrong += after.at(r, c) != (c >= 3 && c < 20 ? src.at(r, c + 2) : before.at(r, c));
  CHECK(wrong == 0);
  // Conversion rounds to nearest even like epona::bf16 (n = 1001: element path; 4096: packs).
  for (const std::int64_t n : {1001, 4096}) {
    const auto x = test::random_tensor({n}, 4, -100.f, 100.f);
    auto y = Tensor<bf16, Cuda>({n});
    cuda::fill_bytes(ctx, y, 0xFF);
    cuda::convert(ctx, upload<float>(x).data(), y.data(), n);
    const auto back = download(y);
    int mismatches = 0;
    for (std::int64_t i = 0; i < n; ++i) mismatches += back.data()[i] != float(bf16(x.data()[i]));
    CHECK(mismatches == 0);
  }
  // Euler update: x += round_V(a * v), two roundings, bit-exact against the host.
  for (const std::int64_t n : {1001, 4096}) {
    const auto x = test::random_tensor({n}, 5), v = test::random_tensor({n}, 6, -3.f, 3.f);
    const float a = 0.0123f;
    auto dx = upload<float>(x);
    cuda::axpy(ctx, dx.data(), upload<float>(v).data(), a, n);
    auto dxb = upload<float>(x);
    const auto vb = upload<bf16>(v);
    cuda::axpy(ctx, dxb.data(), vb.data(), a, n);
    const auto got = download(dx), got_b = download(dxb);
    int wrong_f = 0, wrong_b = 0;
    for (std::int64_t i = 0; i < n; ++i) {
      volatile float step = a * v.data()[i];
      wrong_f += got.data()[i] != x.data()[i] + step;
      const float vbi = float(bf16(v.data()[i]));
      volatile float step_b = a * vbi;
      wrong_b += got_b.data()[i] != x.data()[i] + float(bf16(step_b));
    }
    CHECK(wrong_f == 0);
    CHECK(wrong_b == 0);
    // Fused with the conversion of the new state (the bf16 samplers): the same x, and the
    // rounded state into a poisoned bf16 buffer, bit-exact (n = 1001: element path).
    auto dxc = upload<float>(x);
    auto xc = Tensor<bf16, Cuda>({n});
    cuda::fill_bytes(ctx, xc, 0xFF);
    cuda::axpy_convert(ctx, dxc.data(), vb.data(), a, xc.data(), n);
    const auto got_c = download(dxc), got_xc = download(xc);
    int wrong_c = 0;
    for (std::int64_t i = 0; i < n; ++i)
      wrong_c += got_c.data()[i] != got_b.data()[i] || got_xc.data()[i] != float(bf16(got_b.data()[i]));
    CHECK(wrong_c == 0);
  }
}

namespace {

// qk_norm_rope's row path (a warp per row of a part, 16-byte accesses) against its
// head-per-warp path on the same input: bit-identical (same roundings, same summation tree;
// the head-per-warp path is checked against the CPU's unfused ops in test_cuda_pointwise),
// every other channel untouched. Two segments (the second with fewer queries than keys);
// head counts that leave a partial warp access or group (3, 5, 20), groups of 2, 4 and 8
// accesses; a buffer
// misaligned for 16-byte accesses (the row path declines it: the same result either way).
struct QkRows {
  std::int64_t first, q_first, end;
  const float* q_scale;
  const float* k_scale;
};

template <class T>
void check_qk_rows(std::int64_t heads, std::int64_t rows, std::uint32_t seed, std::int64_t misalign = 0) {
  auto& ctx = gpu();
  const std::int64_t width = heads * 128, stride = 3 * width + 8, pairs = 64;
  auto x = test::random_tensor({rows, stride}, seed, -2.f, 2.f);
  test::round_to<T>(x);
  const auto angle = test::random_tensor({rows, pairs}, seed + 1, -20.f, 20.f);
  Tensor<float, Cpu> cos({rows, pairs}), sin({rows, pairs});
  for (std::int64_t i = 0; i < angle.numel(); ++i) cos.data()[i] = std::cos(angle.data()[i]), sin.data()[i] = std::sin(angle.data()[i]);
  const auto dcos = upload<float>(cos), dsin = upload<float>(sin);
  std::vector<Tensor<float, Cuda>> scales;
  for (std::uint32_t i = 0; i < 4; ++i) scales.push_back(upload<float>(test::random_tensor({128}, seed + 10 + i, 0.5f, 1.5f)));
  const std::int64_t half = rows / 2;
  const std::array<QkRows, 2> segs{QkRows{0, 0, half, scales[0].data(), scales[1].data()},
                                   QkRows{half, half + 3, rows, scales[2].data(), scales[3].data()}};
  const auto run = [&](bool row_path) {  // the row path wherever it can run (not only where it pays)
    auto dx = test::upload<T>(ctx, x, misalign);
    ctx.policy().qk_norm_rope_rows = row_path;
    cuda::detail::qk_rows_forced() = row_path;
    cuda::qk_norm_rope(ctx, dx.data(), stride, width, heads, 128, 1e-6f, dcos.data(), dsin.data(), segs);
    ctx.policy().qk_norm_rope_rows = true;
    cuda::detail::qk_rows_forced() = false;
    return download(dx);
  };
  const auto heads_out = run(false);
  const int default_accesses = cuda::detail::qk_rows_accesses();
  for (const int accesses : {2, 4, 8}) {  // heads per warp: 2, 4, 8 times the heads of one access
    cuda::detail::qk_rows_accesses() = accesses;
    const auto rows_out = run(true);
    const std::int64_t differ = test::count_bit_differences(rows_out, heads_out);
    const std::int64_t changed = test::count_bit_differences(rows_out.data(), x.data(), x.numel(), [&](std::int64_t i) {
      return i % stride >= 2 * width;
    });
    MESSAGE(("qk_norm_rope row path " + std::string(test::type_name<T>())), " accesses ", accesses, " heads ", heads,
            " rows ", rows, " misaligned by ", misalign, ": ", differ, " values differ from the head-per-warp path, ",
            changed, " untouched changed");
    CHECK(differ == 0);
    CHECK(changed == 0);
  }
  cuda::detail::qk_rows_accesses() = default_accesses;
}

}  // namespace

TEST_CASE_TEMPLATE("qk_norm_rope: the row path gives the head-per-warp path's bits", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  check_qk_rows<T>(16, 1027, 950);  // the VisDiT's joint rows
  check_qk_rows<T>(8, 530, 951);    // the TrajDiT's
  check_qk_rows<T>(3, 41, 952);
  check_qk_rows<T>(5, 40, 953);
  check_qk_rows<T>(20, 33, 954);
  check_qk_rows<T>(8, 30, 955, 1);  // declined: the head-per-warp path on both sides
}

namespace {

// One DiT block on the CPU (float32) and on the GPU (weights W) from the same residual z,
// modulation vectors and RoPE table; returns (cpu z or out, gpu z or out).
struct DitBlockCase {
  nn::DitWidths widths = model::FluxDitConfig::vis(config()).widths();
  nn::JointRows rows{config().tokens_per_frame(), config().img_tokens()};
  Tensor<float, Cpu> z = test::random_tensor({rows.total(), widths.hidden}, 21, -2.f, 2.f);
  nn::RopeTable<Cpu> rope = [this] {
    const auto ids = model::prepare_ids(1, config().latent_h(), config().latent_w(), rows.cond, config().traj_len);
    Tensor<float, Cpu> joint({rows.total(), 3});
    std::copy_n(ids.cond.data(), rows.cond * 3, joint.data());
    std::copy_n(ids.img.data(), rows.target * 3, joint.data() + rows.cond * 3);
    return nn::nd_rope_table(joint, {16, 56, 56}, 10000.0);
  }();

  template <class B, class A>
  static nn::DitScratch<B, A> scratch(Arena<B>& arena, std::int64_t n, const nn::DitWidths& w) {
    return nn::DitScratch<B, A>::plan(arena, n, w);
  }

  // run(block, scratch, mods, rope) for CPU float and GPU W; compares z rows [first, total).
  template <class W, class MakeBlock, class Run>
  void compare(const std::string& what, const std::string& prefix, std::int64_t mod_width, MakeBlock make, Run run,
               std::int64_t first = 0, bool whole_z = true) {
    using A = Activation<Cuda, W>;
    const auto mods = test::random_tensor({mod_width}, 22, -0.5f, 0.5f);
    auto cpu_block = make.template operator()<Cpu, float>();
    bind(cpu_block, prefix);
    ArenaCounter<Cpu> counter;
    nn::DitScratch<Cpu, float>::plan(counter, rows.total(), widths);
    Arena<Cpu> ca(counter.bytes());
    auto cs = nn::DitScratch<Cpu, float>::plan(ca, rows.total(), widths);
    std::copy_n(z.data(), z.numel(), cs.z.data());
    Tensor<float, Cpu> cpu_out = run(cpu_ctx(), cpu_block, cs, mods.data(), rope);

    auto gpu_block = make.template operator()<Cuda, W>();
    bind(gpu_block, prefix);
    Arena<Cuda> ga(counter.bytes() * 2);
    poison_arena(ga);
    auto gs = nn::DitScratch<Cuda, A>::plan(ga, rows.total(), widths);
    auto zin = upload<A>(z);
    cuda::copy(gpu(), zin.data(), gs.z.data(), z.numel());
    const auto dmods = upload<A>(mods);
    const nn::RopeTable<Cuda> drope{upload<float>(rope.cos), upload<float>(rope.sin)};
    Tensor<float, Cpu> gpu_out = run(gpu(), gpu_block, gs, dmods.data(), drope);
    if (whole_z) {
      // Rows before `first` are not updated: bit-identical to the (rounded) input.
      const auto zin_host = download(zin);
      int changed = 0;
      for (std::int64_t i = 0; i < first * widths.hidden; ++i) changed += gpu_out.data()[i] != zin_host.data()[i];
      CHECK(changed == 0);
      const auto rows_of = [&](const Tensor<float, Cpu>& t) { return t.slice(first, rows.total()).clone(); };
      expect_close(what, rows_of(gpu_out), rows_of(cpu_out), bound<W>("vis.velocity"));
    } else {
      expect_close(what, gpu_out, cpu_out, bound<W>("vis.velocity"));
    }
  }
};

template <class W>
void dit_blocks() {
  DitBlockCase k;
  const auto w = k.widths;
  const std::int64_t D = w.hidden;
  const auto dl = [w]<class B, class T>() { return nn::DoubleStreamBlock<B, T>(w); };
  const auto sl = [w]<class B, class T>() { return nn::SingleStreamBlock<B, T>(w); };
  const auto ll = [w]<class B, class T>() { return nn::LastLayer<B, T>(w, config().token_dim()); };
  const auto z_of = [](auto& ctx, auto& s) {
    if constexpr (std::is_same_v<std::decay_t<decltype(ctx)>, cuda::Context>)
      return download(s.z);
    else
      return s.z.clone();
  };
  const std::string tag = std::is_same_v<W, float> ? " (GPU f32 vs CPU)" : " (GPU bf16 vs CPU f32)";
  k.template compare<W>("DoubleStreamBlock" + tag, "module.dit.double_blocks.0.", 12 * D, dl,
                        [&](auto& ctx, const auto& b, auto& s, const auto* mods, const auto& rope) {
                          nn::SideQueue<BackendOf_t<decltype(ctx)>> queue;
                          b(ctx, queue, s, k.rows, rope, mods);
                          return z_of(ctx, s);
                        });
  for (const std::int64_t first : {std::int64_t{0}, k.rows.cond})
    k.template compare<W>("SingleStreamBlock, rows from " + std::to_string(first) + tag,
                          "module.dit.single_blocks.1.", 3 * D, sl,
                          [&](auto& ctx, const auto& b, auto& s, const auto* mods, const auto& rope) {
                            nn::SideQueue<BackendOf_t<decltype(ctx)>> queue;
                            b(ctx, queue, s, k.rows, rope, mods, first);
                            return z_of(ctx, s);
                          },
                          first);
  k.template compare<W>("LastLayer" + tag, "module.dit.final_layer.", 2 * D, ll,
                        [&](auto& ctx, const auto& b, auto& s, const auto* mods, const auto&) {
                          using B = typename std::decay_t<decltype(s.z)>::backend;
                          using A = typename std::decay_t<decltype(s.z)>::value_type;
                          Tensor<A, B> out({k.rows.target, config().token_dim()});
                          if constexpr (std::is_same_v<B, Cuda>) cuda::fill_bytes(gpu(), out, 0xFF);
                          b(ctx, s, k.rows, mods, out);
                          if constexpr (std::is_same_v<B, Cuda>)
                            return download(out);
                          else
                            return out;
                        },
                        0, false);
}

}  // namespace

TEST_CASE("DiT blocks on the GPU vs the CPU: float32 and bf16") {
  EPONA_REQUIRE_GPU();
  dit_blocks<float>();
  dit_blocks<bf16>();
}

namespace {

std::int64_t kBatch = 2;

Tensor<float, Cpu> scaled(Tensor<float, Cpu> t, float k) {
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] *= k;
  return t;
}

template <class W>
void mst_blocks() {
  const auto& c = config();
  const auto cfg = model::MstConfig::from(c);
  model::SpatialTemporalTransformer<Cpu, float> cpu_mst(cfg);
  model::SpatialTemporalTransformer<Cuda, W> gpu_mst(cfg);
  bind(cpu_mst, "module.model.");
  bind(gpu_mst, "module.model.");
  const auto latents = test::random_tensor({kBatch, c.condition_frames, c.img_tokens(), c.token_dim()}, 31, -2.f, 2.f);
  const auto tok = model::PoseTokenizer::from(c);
  const auto pose_idx = tok.poses_to_indices(scaled(test::random_tensor({kBatch, c.condition_frames + 1, 2}, 32), 3.f));
  const auto yaw_idx = tok.yaws_to_indices(scaled(test::random_tensor({kBatch, c.condition_frames + 1, 1}, 33), 4.f));
  const std::string tag = std::is_same_v<W, float> ? " (GPU f32 vs CPU)" : " (GPU bf16 vs CPU f32)";
  for (const bool observed : {true, false}) {
    std::map<std::string, Tensor<float, Cpu>> cpu_stages;
    Tensor<float, Cpu> stt({kBatch, c.tokens_per_frame(), c.n_embd}), emb({kBatch, c.pose_emb_dim()});
    Arena<Cpu> ca(cpu_mst.evaluate_workspace_bytes(kBatch));
    model::MstObserver<Cpu> cpu_obs = [&](std::int64_t b, const std::string& stage, const Tensor<float, Cpu>& x) {
      cpu_stages[stage + std::to_string(b)] = x.clone();
    };
    cpu_mst.evaluate(cpu_ctx(), ca, latents, pose_idx, yaw_idx, stt, emb, observed ? cpu_obs : nullptr);

    auto dstt = Tensor<float, Cuda>({kBatch, c.tokens_per_frame(), c.n_embd});
    auto demb = Tensor<float, Cuda>({kBatch, c.pose_emb_dim()});
    cuda::fill_bytes(gpu(), dstt, 0xFF);
    cuda::fill_bytes(gpu(), demb, 0xFF);
    Arena<Cuda> ga(gpu_mst.evaluate_workspace_bytes(kBatch));
    poison_arena(ga);
    int seen = 0;
    model::MstObserver<Cuda> gpu_obs = [&](std::int64_t b, const std::string& stage, const Tensor<float, Cuda>& x) {
      const std::string recipe = stage == "tokens_in" ? "mst.tokens_in" : "mst.block0_out";
      expect_close("MST " + stage + "[" + std::to_string(b) + "]" + tag, download(x),
                   cpu_stages.at(stage + std::to_string(b)), bound<W>(recipe));
      ++seen;
    };
    gpu_mst.evaluate(gpu(), ga, upload<float>(latents), pose_idx, yaw_idx, dstt, demb, observed ? gpu_obs : nullptr);
    CHECK(ga.high_water() <= gpu_mst.evaluate_workspace_bytes(kBatch));
    if (observed) CHECK(seen == kBatch * (1 + c.mst_depth()));
    const std::string how = observed ? ", observed" : ", pruned";
    expect_close("MST stt_features" + how + tag, download(dstt), stt, bound<W>("mst.stt_features"));
    expect_close("MST pose_emb" + how + tag, download(demb), emb, bound<W>("mst.pose_emb"));
  }
}

// A whole DiT (batch 2): forward and a 10-step sample, CPU float32 vs GPU.
template <class W>
void dit_network(bool vis) {
  const auto& c = config();
  const auto dc = vis ? model::FluxDitConfig::vis(c) : model::FluxDitConfig::traj(c);
  const std::string prefix = vis ? "module.dit." : "module.traj_dit.", name = vis ? "vis" : "traj";
  model::FluxDiT<Cpu, float> cpu_dit(dc);
  model::FluxDiT<Cuda, W> gpu_dit(dc);
  bind(cpu_dit, prefix);
  bind(gpu_dit, prefix);
  const auto ids = model::prepare_ids(kBatch, c.latent_h(), c.latent_w(), c.tokens_per_frame(), c.traj_len);
  const auto& target_ids = vis ? ids.img : ids.traj;
  const std::int64_t Lx = target_ids.size(1);
  const nn::JointRows rows{c.tokens_per_frame(), Lx};
  const auto cond = test::random_tensor({kBatch, rows.cond, c.n_embd}, 41, -2.f, 2.f);
  const auto y = test::random_tensor({kBatch, c.pose_emb_dim()}, 42, -2.f, 2.f);
  const auto x = test::random_tensor({kBatch, Lx, dc.in_channels}, 43, -2.f, 2.f);
  Tensor<float, Cpu> t({kBatch});
  t.data()[0] = 0.3f, t.data()[1] = 0.85f;
  const auto grid = flow::get_schedule(c.num_sampling_steps, Lx);
  const std::string tag = std::is_same_v<W, float> ? " (GPU f32 vs CPU)" : " (GPU bf16 vs CPU f32)";

  Tensor<float, Cpu> v_cpu(x.shape());
  auto sample_cpu = x.clone();
  {
    Arena<Cpu> arena(std::max(cpu_dit.forward_bytes(kBatch, rows),
                              cpu_dit.conditioning_bytes(kBatch, rows) + cpu_dit.sample_bytes(kBatch, rows, grid.size() - 1)));
    cpu_dit.forward(cpu_ctx(), arena, x, target_ids, cond, ids.cond, t, y, v_cpu);
    arena.reset();
    const auto cc = cpu_dit.prepare(cpu_ctx(), arena, cond, ids.cond, target_ids, y);
    cpu_dit.sample(cpu_ctx(), arena, cc, grid, sample_cpu);
  }
  const auto dcond = upload<float>(cond), dy = upload<float>(y), dx = upload<float>(x);
  Arena<Cuda> arena(std::max(gpu_dit.forward_bytes(kBatch, rows),
                             gpu_dit.conditioning_bytes(kBatch, rows) + gpu_dit.sample_bytes(kBatch, rows, grid.size() - 1)));
  poison_arena(arena);
  auto v = Tensor<Activation<Cuda, W>, Cuda>(x.shape());
  cuda::fill_bytes(gpu(), v, 0xFF);
  gpu_dit.forward(gpu(), arena, dx, target_ids, dcond, ids.cond, t, dy, v);
  {
    // forward_bytes is exactly what forward takes (a poisoned arena's high water is its capacity).
    Arena<Cuda> exact(gpu_dit.forward_bytes(kBatch, rows));
    auto v2 = Tensor<Activation<Cuda, W>, Cuda>(x.shape());
    gpu_dit.forward(gpu(), exact, dx, target_ids, dcond, ids.cond, t, dy, v2);
    CHECK(exact.high_water() == gpu_dit.forward_bytes(kBatch, rows));
  }
  expect_close(name + " DiT forward, batch 2" + tag, download(v), v_cpu, bound<W>(name + ".velocity"));
  auto state = upload<float>(x);  // one state for every run: the recorded loop's key holds its address
  const auto sample_gpu = [&] {
    poison_arena(arena);
    BackendTraits<Cuda>::upload_into(gpu(), x, state);
    ArenaScope<Cuda> scope(arena);
    const auto gc = gpu_dit.prepare(gpu(), arena, dcond, ids.cond, target_ids, dy);
    gpu_dit.sample(gpu(), arena, gc, grid, state);
    return download(state);
  };
  Tensor<float, Cpu> sampled;
  for (int run = 0; run < 2; ++run) {  // the second run replays the recorded graph
    sampled = sample_gpu();
    expect_close(name + " DiT 10-step sample, batch 2, run " + std::to_string(run) + tag, sampled, sample_cpu,
                 bound<W>(name + ".sample.out", 1e-4));
  }
  if (gpu().policy().graphs) CHECK(gpu_dit.sampler_graph().captures() == 1);
  // The sampler's pipelined condition front changes no bit of the sample: off against on.
  gpu_dit.set_sampler_options({false});
  const auto unpipelined = sample_gpu();
  const std::int64_t differ = test::count_bit_differences(unpipelined, sampled);
  MESSAGE(name, " sample without the pipelined condition front", tag, ": ", differ, " of ", unpipelined.numel(),
          " values differ from the default's");
  CHECK(differ == 0);
  gpu_dit.set_sampler_options({});
}

// A whole DiT (batch 2) sampled with each higher-order flow solver, 6 steps: CPU float32 vs the
// GPU's recorded graph (its scratch states taken before the capture), run twice (the second
// replays the graph), one capture per solver; sample_bytes covers what sample takes.
template <class W>
void dit_solvers(bool vis) {
  const auto& c = config();
  const auto dc = vis ? model::FluxDitConfig::vis(c) : model::FluxDitConfig::traj(c);
  const std::string prefix = vis ? "module.dit." : "module.traj_dit.", name = vis ? "vis" : "traj";
  model::FluxDiT<Cpu, float> cpu_dit(dc);
  model::FluxDiT<Cuda, W> gpu_dit(dc);
  bind(cpu_dit, prefix);
  bind(gpu_dit, prefix);
  const auto ids = model::prepare_ids(kBatch, c.latent_h(), c.latent_w(), c.tokens_per_frame(), c.traj_len);
  const auto& target_ids = vis ? ids.img : ids.traj;
  const std::int64_t Lx = target_ids.size(1), steps = 6;
  const nn::JointRows rows{c.tokens_per_frame(), Lx};
  const auto cond = test::random_tensor({kBatch, rows.cond, c.n_embd}, 41, -2.f, 2.f);
  const auto y = test::random_tensor({kBatch, c.pose_emb_dim()}, 42, -2.f, 2.f);
  const auto x = test::random_tensor({kBatch, Lx, dc.in_channels}, 43, -2.f, 2.f);
  const auto grid = flow::get_schedule(steps, Lx);
  const std::string tag = std::is_same_v<W, float> ? " (GPU f32 vs CPU)" : " (GPU bf16 vs CPU f32)";
  const auto dcond = upload<float>(cond), dy = upload<float>(y);
  for (const auto kind : {flow::SolverKind::heun, flow::SolverKind::midpoint, flow::SolverKind::dpmpp2m}) {
    const std::string what = name + " DiT " + flow::solver_name(kind) + " x 6 steps, batch 2";
    auto sample_cpu = x.clone();
    {
      Arena<Cpu> arena(cpu_dit.conditioning_bytes(kBatch, rows) + cpu_dit.sample_bytes(kBatch, rows, steps, kind));
      const auto cc = cpu_dit.prepare(cpu_ctx(), arena, cond, ids.cond, target_ids, y);
      cpu_dit.sample(cpu_ctx(), arena, cc, grid, sample_cpu, kind);
    }
    Arena<Cuda> arena(gpu_dit.conditioning_bytes(kBatch, rows) + gpu_dit.sample_bytes(kBatch, rows, steps, kind));
    const auto captures_before = gpu_dit.sampler_graph().captures();
    Tensor<float, Cpu> first;
    for (int run = 0; run < 2; ++run) {
      poison_arena(arena);
      auto state = upload<float>(x);
      ArenaScope<Cuda> scope(arena);
      const auto gc = gpu_dit.prepare(gpu(), arena, dcond, ids.cond, target_ids, dy);
      gpu_dit.sample(gpu(), arena, gc, grid, state, kind);
      const auto sampled = download(state);
      expect_close(what + ", run " + std::to_string(run) + tag, sampled, sample_cpu, bound<W>(name + ".sample.out", 1e-4));
      if (run == 0) first = sampled;
      else CHECK(test::count_bit_differences(first, sampled) == 0);  // the replay gives the recording's bits
    }
    if (gpu().policy().graphs) CHECK(gpu_dit.sampler_graph().captures() == captures_before + 1);
  }
}

// Item b of a batch, as a batch of one.
Tensor<float, Cpu> one(const Tensor<float, Cpu>& t, std::int64_t b) {
  Shape s = t.shape();
  s[0] = 1;
  return t.slice(b, b + 1).clone().reshape(s);
}

// Batch invariance on the GPU: a batch of 4 scenes (each its own condition, action, noise)
// sampled in one pass through the blocks gives each item what it gives sampled alone, 10 steps.
// float32 within 1e-6 relative; bf16 within the sample's bound (the batched products may take
// other cuBLASLt kernels than one item's, so bits may differ); the bit differences are printed.
template <class W>
void dit_batch_invariance(bool vis) {
  const auto& c = config();
  const auto dc = vis ? model::FluxDitConfig::vis(c) : model::FluxDitConfig::traj(c);
  const std::string name = vis ? "vis" : "traj";
  model::FluxDiT<Cuda, W> dit(dc);
  bind(dit, vis ? "module.dit." : "module.traj_dit.");
  constexpr std::int64_t items = 4;
  const std::int64_t steps = 10;
  const auto sample = [&](const Tensor<float, Cpu>& cond, const Tensor<float, Cpu>& y, const Tensor<float, Cpu>& x) {
    const std::int64_t batch = cond.size(0);
    const auto ids = model::prepare_ids(batch, c.latent_h(), c.latent_w(), c.tokens_per_frame(), c.traj_len);
    const auto& target_ids = vis ? ids.img : ids.traj;
    const nn::JointRows rows{c.tokens_per_frame(), target_ids.size(1)};
    Arena<Cuda> arena(dit.conditioning_bytes(batch, rows) + dit.sample_bytes(batch, rows, steps));
    poison_arena(arena);
    auto state = upload<float>(x);
    const auto dcond = upload<float>(cond), dy = upload<float>(y);
    const auto gc = dit.prepare(gpu(), arena, dcond, ids.cond, target_ids, dy);
    dit.sample(gpu(), arena, gc, flow::get_schedule(steps, rows.target), state);
    return download(state);
  };
  const auto ids = model::prepare_ids(items, c.latent_h(), c.latent_w(), c.tokens_per_frame(), c.traj_len);
  const std::int64_t Lx = (vis ? ids.img : ids.traj).size(1);
  const auto cond = test::random_tensor({items, c.tokens_per_frame(), c.n_embd}, 51, -2.f, 2.f);
  const auto y = test::random_tensor({items, c.pose_emb_dim()}, 52, -2.f, 2.f);
  const auto x = test::random_tensor({items, Lx, dc.in_channels}, 53, -2.f, 2.f);
  const auto batched = sample(cond, y, x);
  double worst = 0;
  std::int64_t differ = 0;
  for (std::int64_t b = 0; b < items; ++b) {
    const auto alone = sample(one(cond, b), one(y, b), one(x, b));
    const auto mine = one(batched, b);
    worst = std::max(worst, test::rel_max(mine, alone));
    differ += test::count_bit_differences(mine, alone);
  }
  const double limit = std::is_same_v<W, float> ? 1e-6 : bound<W>(name + ".sample.out", 1e-4);
  // A std::string: doctest prints a char* as a pointer.
  const std::string type = std::is_same_v<W, float> ? "float32" : "bf16";
  MESSAGE(name, " DiT ", steps, "-step sample, batch ", items, " in one pass vs each item alone (", type, "): worst rel ",
          worst, " (limit ", limit, "), ", differ, " of ", batched.numel(), " values differ in some bit");
  CHECK(worst <= limit);
  CHECK(test::rel_max(one(batched, 0), one(batched, 1)) > 1e-2);  // the items' results do differ
}

// Batch invariance of the MST on the GPU: 10 windows, folded as a pass of kMaxFoldedItems and
// one of 2, give each item what it gives alone (stt_features and pose_emb), and get_pose_emb
// of the batch gives each item's alone. float32 within 1e-6 relative, bf16 within the MST's bound.
template <class W>
void mst_batch_invariance() {
  const auto& c = config();
  const auto cfg = model::MstConfig::from(c);
  model::SpatialTemporalTransformer<Cuda, W> mst(cfg);
  bind(mst, "module.model.");
  const std::int64_t items = model::SpatialTemporalTransformer<Cuda, W>::kMaxFoldedItems + 2, F = c.condition_frames;
  const auto latents = test::random_tensor({items, F, c.img_tokens(), c.token_dim()}, 61, -2.f, 2.f);
  const auto tok = model::PoseTokenizer::from(c);
  const auto pose_idx = tok.poses_to_indices(scaled(test::random_tensor({items, F + 1, 2}, 62), 3.f));
  const auto yaw_idx = tok.yaws_to_indices(scaled(test::random_tensor({items, F + 1, 1}, 63), 4.f));
  const auto run = [&](const Tensor<float, Cpu>& lat, const Tensor<float, Cpu>& pose, const Tensor<float, Cpu>& yaw) {
    const std::int64_t n = lat.size(0);
    auto stt = Tensor<float, Cuda>({n, c.tokens_per_frame(), c.n_embd});
    auto emb = Tensor<float, Cuda>({n, c.pose_emb_dim()}), one_emb = Tensor<float, Cuda>({n, c.pose_emb_dim()});
    for (auto* t : {&stt, &emb, &one_emb}) cuda::fill_bytes(gpu(), *t, 0xFF);
    Arena<Cuda> arena(std::max(mst.evaluate_workspace_bytes(n), mst.pose_emb_workspace_bytes(n)));
    poison_arena(arena);
    mst.evaluate(gpu(), arena, upload<float>(lat), pose, yaw, stt, emb);
    CHECK(arena.high_water() <= mst.evaluate_workspace_bytes(n));
    arena.reset();
    Tensor<float, Cpu> last_pose({n, 1, 2}), last_yaw({n, 1, 1});
    for (std::int64_t b = 0; b < n; ++b) {
      last_pose.at(b, 0, 0) = pose.at(b, F, 0), last_pose.at(b, 0, 1) = pose.at(b, F, 1);
      last_yaw.at(b, 0, 0) = yaw.at(b, F, 0);
    }
    mst.get_pose_emb(gpu(), arena, last_pose, last_yaw, one_emb);
    return std::array<Tensor<float, Cpu>, 3>{download(stt), download(emb), download(one_emb)};
  };
  const auto batched = run(latents, pose_idx, yaw_idx);
  double worst[3] = {0, 0, 0};
  for (std::int64_t b = 0; b < items; ++b) {
    const auto alone = run(one(latents, b), one(pose_idx, b), one(yaw_idx, b));
    for (int k = 0; k < 3; ++k) worst[k] = std::max(worst[k], test::rel_max(one(batched[k], b), alone[k]));
  }
  const bool f32 = std::is_same_v<W, float>;
  const double limits[3] = {f32 ? 1e-6 : bound<W>("mst.stt_features"), f32 ? 1e-6 : bound<W>("mst.pose_emb"),
                            f32 ? 1e-6 : bound<W>("mst.pose_emb")};
  const char* names[3] = {"stt_features", "pose_emb", "get_pose_emb"};
  for (int k = 0; k < 3; ++k) {
    MESSAGE("MST batch of ", items, " (", std::string(f32 ? "float32" : "bf16"), ") vs each item alone, ",
            std::string(names[k]), ": worst rel ", worst[k], " (limit ", limits[k], ")");
    CHECK(worst[k] <= limits[k]);
  }
  CHECK(test::rel_max(one(batched[0], 0), one(batched[0], 1)) > 1e-2);  // the items' results do differ
}

}  // namespace

TEST_CASE("MST batches folded into one pass on the GPU: each item as evaluated alone") {
  EPONA_REQUIRE_GPU();
  mst_batch_invariance<float>();
  mst_batch_invariance<bf16>();
}

TEST_CASE("MST on the GPU vs the CPU, block by block (batch 2): float32 and bf16") {
  EPONA_REQUIRE_GPU();
  mst_blocks<float>();
  mst_blocks<bf16>();
}

TEST_CASE("VisDiT and TrajDiT networks on the GPU vs the CPU (batch 2): forward and 10-step sample") {
  EPONA_REQUIRE_GPU();
  for (const bool vis : {false, true}) {
    dit_network<float>(vis);
    dit_network<bf16>(vis);
  }
}

TEST_CASE("VisDiT and TrajDiT sampled with Heun, midpoint and DPM-Solver++(2M) on the GPU vs the CPU") {
  EPONA_REQUIRE_GPU();
  for (const bool vis : {false, true}) {
    dit_solvers<float>(vis);
    dit_solvers<bf16>(vis);
  }
}

TEST_CASE("world-model steps on the GPU vs the CPU: plan and predict_next with a given action (float32)") {
  EPONA_REQUIRE_GPU();
  const auto& c = config();
  auto cpu_wm = WorldModel<Cpu, float>::load(weights(), c);
  auto gpu_wm = WorldModel<Cuda, float>::load(weights(), c);
  const History h{test::random_tensor({1, c.condition_frames, c.img_tokens(), c.token_dim()}, 51, -2.f, 2.f),
                  scaled(test::random_tensor({1, c.condition_frames, 2}, 52, 0.f, 1.f), 4.f),
                  test::random_tensor({1, c.condition_frames, 1}, 53)};
  SampleOptions opt;
  opt.seed = 5;
  expect_close("plan (GPU f32 vs CPU)", gpu_wm.plan(h, opt), cpu_wm.plan(h, opt), 1e-4);
  const NextAction a{scaled(test::random_tensor({1, 1, 2}, 54, 0.f, 1.f), 3.f), test::random_tensor({1, 1, 1}, 55)};
  const auto r_cpu = cpu_wm.predict_next(h, a, opt), r_gpu = gpu_wm.predict_next(h, a, opt);
  CHECK(r_gpu.trajectory.empty());
  expect_close("predict_next latent, given action (GPU f32 vs CPU)", r_gpu.latent, r_cpu.latent, 1e-4);
}

TEST_CASE("world-model steps with per-DiT solvers on the GPU vs the CPU (float32): the engine's --solver path") {
  EPONA_REQUIRE_GPU();
  const auto& c = config();
  auto cpu_wm = WorldModel<Cpu, float>::load(weights(), c);
  auto gpu_wm = WorldModel<Cuda, float>::load(weights(), c);
  const History h{test::random_tensor({1, c.condition_frames, c.img_tokens(), c.token_dim()}, 61, -2.f, 2.f),
                  scaled(test::random_tensor({1, c.condition_frames, 2}, 62, 0.f, 1.f), 4.f),
                  test::random_tensor({1, c.condition_frames, 1}, 63)};
  SampleOptions opt;
  opt.seed = 9, opt.plan_solver = flow::SolverKind::midpoint, opt.plan_steps = 5;
  opt.video_solver = flow::SolverKind::dpmpp2m, opt.video_steps = 7;
  for (int run = 0; run < 2; ++run) {  // the second replays both DiTs' recorded loops
    const auto r_cpu = cpu_wm.predict_next(h, std::nullopt, opt), r_gpu = gpu_wm.predict_next(h, std::nullopt, opt);
    expect_close("self-predicted step, midpoint x 5 / dpmpp2m x 7, trajectory (GPU f32 vs CPU)", r_gpu.trajectory,
                 r_cpu.trajectory, 1e-4);
    expect_close("self-predicted step, midpoint x 5 / dpmpp2m x 7, latent (GPU f32 vs CPU)", r_gpu.latent, r_cpu.latent,
                 1e-4);
  }
}

TEST_CASE("VisDiT and TrajDiT batches in one pass on the GPU: each item as sampled alone") {
  EPONA_REQUIRE_GPU();
  for (const bool vis : {false, true}) {
    dit_batch_invariance<float>(vis);
    dit_batch_invariance<bf16>(vis);
  }
}
