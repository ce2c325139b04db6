// The FLUX-style DiT blocks (DoubleStreamBlock, SingleStreamBlock, LastLayer, MLPEmbedders,
// 3-axis RoPE) composed into a VisDiT- and a TrajDiT-shaped network at head dim 128 (the real
// head dim; the golden set only has 32 and 24), against a float64 implementation written from
// world-model.md §3, §6, §7 — weights stored as float32 and as bfloat16 (bound into float and
// bf16 layers). Tolerance rel <= 1e-4 for float layers, 1e-2 for bf16 layers (whose GEMMs may
// round activations to bf16); the arena use must equal the planned bytes.
#include <doctest/doctest.h>

#include <string>

#include "epona/model/flux_dit.hpp"
#include "epona/model/pose_tokenizer.hpp"
#include "world_reference.hpp"

using namespace epona;
using world_ref::HostTensor;
using world_ref::i64;
using world_ref::RandomWeights;
using world_ref::Vec;

namespace {

model::FluxDitConfig small_config(bool vis) {
  model::FluxDitConfig c;
  c.in_channels = c.out_channels = vis ? 4 : 3;
  c.context_in_dim = 96;
  c.hidden_size = 256;
  c.num_heads = 2;  // head dim 128
  c.depth = vis ? 2 : 1;
  c.depth_single_blocks = vis ? 2 : 1;
  c.vec_in_dim = vis ? 48 : 0;
  c.axes_dim = {16, 56, 56};
  c.input_name = vis ? "img_in" : "traj_in";
  return c;
}

// ---- float64 reference of one batch item ----
struct RefDit {
  const RandomWeights& w;
  const model::FluxDitConfig& c;
  i64 D, Dm, H, d;
  std::vector<Vec> angle;  // (rows, d/2) RoPE angles of the joint sequence

  Vec lin(const std::string& p, const Vec& x, i64 n, i64 in, i64 out) const {
    return world_ref::linear(w, p, x, n, in, out, true);
  }
  Vec mod(const std::string& p, const Vec& silu_vec, i64 chunks) const { return lin(p, silu_vec, 1, D, chunks * D); }

  // Joint attention over rows [cond | target] of packed qkv (3D wide), RMS-normed q/k given.
  Vec attend(Vec qkv, i64 n) const {
    world_ref::rope(qkv, n, 3 * D, 0, H, d, angle);
    world_ref::rope(qkv, n, 3 * D, D, H, d, angle);
    return world_ref::attention(qkv, n, 3 * D, 0, D, 2 * D, H, d, false);
  }

  void double_block(const std::string& p, Vec& cond, i64 lc, Vec& x, i64 lx, const Vec& sv) const {
    const Vec mc = mod(p + "cond_mod.lin.", sv, 6), mx = mod(p + "img_mod.lin.", sv, 6);
    auto qkv_of = [&](const std::string& s, const Vec& z, i64 n, const Vec& m) {
      Vec q = lin(p + s + "_attn.qkv.", world_ref::modulate(z, n, D, 1e-6, &m[0], &m[D]), n, D, 3 * D);
      world_ref::rms_heads(q, n, 3 * D, 0, H, d, w[p + s + "_attn.norm.query_norm.scale"], 1e-6);
      world_ref::rms_heads(q, n, 3 * D, D, H, d, w[p + s + "_attn.norm.key_norm.scale"], 1e-6);
      return q;
    };
    Vec joint = qkv_of("cond", cond, lc, mc);
    const Vec qx = qkv_of("img", x, lx, mx);
    joint.insert(joint.end(), qx.begin(), qx.end());
    const Vec o = attend(joint, lc + lx);
    auto finish = [&](const std::string& s, Vec& z, i64 n, i64 first, const Vec& m) {
      const Vec a = lin(p + s + "_attn.proj.", Vec(o.begin() + first * D, o.begin() + (first + n) * D), n, D, D);
      for (i64 i = 0; i < n * D; ++i) z[i] += m[2 * D + i % D] * a[i];
      Vec h = world_ref::map(lin(p + s + "_mlp.0.", world_ref::modulate(z, n, D, 1e-6, &m[3 * D], &m[4 * D]), n, D, Dm),
                             world_ref::gelu_tanh);
      const Vec y = lin(p + s + "_mlp.2.", h, n, Dm, D);
      for (i64 i = 0; i < n * D; ++i) z[i] += m[5 * D + i % D] * y[i];
    };
    finish("img", x, lx, lc, mx);
    finish("cond", cond, lc, 0, mc);
  }

  void single_block(const std::string& p, Vec& z, i64 n, const Vec& sv) const {
    const Vec m = mod(p + "modulation.lin.", sv, 3);
    const Vec h = lin(p + "linear1.", world_ref::modulate(z, n, D, 1e-6, &m[0], &m[D]), n, D, 3 * D + Dm);
    Vec qkv(static_cast<std::size_t>(n * 3 * D));
    for (i64 r = 0; r < n; ++r) std::copy_n(&h[r * (3 * D + Dm)], 3 * D, &qkv[r * 3 * D]);
    world_ref::rms_heads(qkv, n, 3 * D, 0, H, d, w[p + "norm.query_norm.scale"], 1e-6);
    world_ref::rms_heads(qkv, n, 3 * D, D, H, d, w[p + "norm.key_norm.scale"], 1e-6);
    const Vec o = attend(qkv, n);
    Vec cat(static_cast<std::size_t>(n * (D + Dm)));
    for (i64 r = 0; r < n; ++r) {
      std::copy_n(&o[r * D], D, &cat[r * (D + Dm)]);
      for (i64 i = 0; i < Dm; ++i) cat[r * (D + Dm) + D + i] = world_ref::gelu_tanh(h[r * (3 * D + Dm) + 3 * D + i]);
    }
    const Vec y = lin(p + "linear2.", cat, n, D + Dm, D);
    for (i64 i = 0; i < n * D; ++i) z[i] += m[2 * D + i % D] * y[i];
  }

  Vec velocity(const Vec& x_in, i64 lx, const Vec& cond_in, i64 lc, double t, const Vec& y) const {
    Vec x = lin(c.input_name + ".", x_in, lx, c.in_channels, D);
    Vec cond = lin("cond_in.", cond_in, lc, c.context_in_dim, D);
    Vec vec = lin("time_in.out_layer.",
                  world_ref::map(lin("time_in.in_layer.", world_ref::timestep(t, c.time_dim, 1e4, 1e3), 1, c.time_dim, D),
                                 world_ref::silu),
                  1, D, D);
    if (c.vec_in_dim) {
      const Vec v = lin("vector_in.out_layer.",
                        world_ref::map(lin("vector_in.in_layer.", y, 1, c.vec_in_dim, D), world_ref::silu), 1, D, D);
      for (i64 i = 0; i < D; ++i) vec[i] += v[i];
    }
    const Vec sv = world_ref::map(vec, world_ref::silu);
    for (i64 i = 0; i < c.depth; ++i) double_block("double_blocks." + std::to_string(i) + ".", cond, lc, x, lx, sv);
    Vec z = cond;
    z.insert(z.end(), x.begin(), x.end());
    for (i64 j = 0; j < c.depth_single_blocks; ++j) single_block("single_blocks." + std::to_string(j) + ".", z, lc + lx, sv);
    const Vec m = mod("final_layer.adaLN_modulation.1.", sv, 2);
    const Vec tgt(z.begin() + lc * D, z.end());
    return lin("final_layer.linear.", world_ref::modulate(tgt, lx, D, 1e-6, &m[0], &m[D]), lx, D, c.out_channels);
  }
};

template <class W>
void check_dit(bool vis, bool bf16_storage) {
  const auto c = small_config(vis);
  RandomWeights w(vis ? 101 : 202, bf16_storage);
  model::FluxDiT<Cpu, W> dit(c);
  w.add_all(dit.parameters());
  io::BindReport report(w.map());
  dit.bind(w.map(), "", report);
  report.finish(true);

  const i64 B = 2, lc = 7, lx = vis ? 6 : 5;
  const auto ids = model::prepare_ids(B, 2, 3, lc, lx);  // image ids [0, row, col] on a 2 x 3 grid
  const HostTensor& x_ids = vis ? ids.img : ids.traj;
  const auto x = world_ref::random_tensor({B, lx, c.in_channels}, 1);
  const auto cond = world_ref::random_tensor({B, lc, c.context_in_dim}, 2, -2.f, 2.f);
  const auto y = world_ref::random_tensor({B, 48}, 3);
  HostTensor t({B});
  t.data()[0] = 0.25f;
  t.data()[1] = 0.875f;
  HostTensor out({B, lx, c.out_channels});
  cpu::Context ctx(2);
  const nn::JointRows rows{lc, lx};
  Arena<Cpu> arena(dit.forward_bytes(B, rows));
  dit.forward(ctx, arena, x, x_ids, cond, ids.cond, t, y, out);
  CHECK(arena.high_water() == dit.forward_bytes(B, rows));

  for (i64 b = 0; b < B; ++b) {
    RefDit ref{w, c, c.hidden_size, c.mlp_ratio * c.hidden_size, c.num_heads, c.hidden_size / c.num_heads, {}};
    for (i64 r = 0; r < lc + lx; ++r) {  // joint ids: condition tokens (all 0), then the target ids
      Vec a;
      for (std::size_t axis = 0; axis < c.axes_dim.size(); ++axis)
        for (i64 m = 0; m < c.axes_dim[axis] / 2; ++m) {
          const double pos = r < lc ? 0.0 : double(x_ids.at(b, r - lc, i64(axis)));
          a.push_back(pos / std::pow(1e4, 2.0 * m / double(c.axes_dim[axis])));
        }
      ref.angle.push_back(a);
    }
    const Vec expected = ref.velocity(world_ref::to_vec(x[b]), lx, world_ref::to_vec(cond[b]), lc, t.data()[b],
                                      world_ref::to_vec(y[b]));
    const double rel = world_ref::rel_max(out[b], expected);
    const std::string what = std::string(vis ? "VisDiT" : "TrajDiT") + "-shaped DiT, head dim 128, " +
                             (bf16_storage ? "bf16" : "fp32") + " checkpoint, " +
                             (std::is_same_v<W, float> ? "float" : "bf16") + " layers, item " + std::to_string(b);
    // bf16 layers: the CPU GEMM may round its inputs to bf16 as well (AVX512-BF16 dot products,
    // like autocast), ~2^-9 per product input, so their bound is bf16-sized.
    const double tol = std::is_same_v<W, float> ? 1e-4 : 1e-2;
    MESSAGE(what, ": rel ", rel, " (limit ", tol, ")");
    CHECK(rel <= tol);
  }
}

}  // namespace

TEST_CASE("VisDiT-shaped network (vector_in, 2 double + 2 single blocks) vs float64") {
  check_dit<float>(true, false);
}
TEST_CASE("TrajDiT-shaped network (traj_in, no vector_in, 1 + 1 blocks) vs float64") {
  check_dit<float>(false, false);
}
TEST_CASE("a bfloat16 checkpoint binds into float layers (exact) and bf16 layers (bf16 GEMMs)") {
  check_dit<float>(true, true);
  check_dit<bf16>(true, true);
  check_dit<bf16>(false, true);
}
