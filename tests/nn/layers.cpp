// The world model's small layers against float64 loops on random weights bound by their
// official names: Linear (+ row views), LayerNorm (affine / not), SequentialMlp (erf / tanh
// GELU), MlpEmbedder, Modulation (chunk order), QkNorm, packed attention in the MST's time
// (causal, strided across frames) and space layouts. Tolerance: rel <= 1e-5 (fp32 vs fp64).
#include <doctest/doctest.h>

#include "epona/nn/attention.hpp"
#include "epona/nn/layer_norm.hpp"
#include "epona/nn/linear.hpp"
#include "epona/nn/mlp.hpp"
#include "epona/nn/modulation.hpp"
#include "world_reference.hpp"

using namespace epona;
using world_ref::HostTensor;
using world_ref::i64;
using world_ref::Vec;

namespace {
cpu::Context& ctx() {
  static cpu::Context c(2);
  return c;
}
template <class Layer>
void bind_strict(Layer& layer, const world_ref::RandomWeights& w, const std::string& prefix) {
  io::BindReport r(w.map());
  layer.bind(w.map(), prefix, r);
  r.finish(true, [&](const std::string& k) { return k.rfind(prefix, 0) != 0; });  // strict within prefix
}
void expect_rel(const std::string& what, const HostTensor& got, const Vec& ref, double tol = 1e-5) {
  const double rel = world_ref::rel_max(got, ref);
  MESSAGE(what, ": rel ", rel);
  CHECK(rel <= tol);
}
}  // namespace

TEST_CASE("Linear with and without bias, and a row view of it") {
  world_ref::RandomWeights w(1);
  w.linear("lin.", 33, 70, true);
  nn::Linear<Cpu, float> lin(33, 70, true);
  bind_strict(lin, w, "lin.");
  const auto x = world_ref::random_tensor({5, 33}, 2);
  HostTensor y({5, 70});
  lin(ctx(), x, y);
  expect_rel("linear", y, world_ref::linear(w, "lin.", world_ref::to_vec(x), 5, 33, 70, true));
  const auto part = lin.rows(20, 50);
  HostTensor yp({5, 30});
  part(ctx(), x, yp);
  for (i64 r = 0; r < 5; ++r)
    for (i64 c = 0; c < 30; ++c) CHECK(yp.at(r, c) == doctest::Approx(y.at(r, 20 + c)).epsilon(1e-6));
}

TEST_CASE("LayerNorm: affine eps 1e-5 and parameter-free eps 1e-6") {
  world_ref::RandomWeights w(3);
  w.layer_norm("ln.", 48);
  nn::LayerNorm<Cpu> affine(48, 1e-5f, true), plain(48, 1e-6f, false);
  bind_strict(affine, w, "ln.");
  auto x = world_ref::random_tensor({6, 48}, 4, -3.f, 5.f);
  HostTensor y({6, 48});
  affine(ctx(), x, y);
  expect_rel("layer norm (affine)", y, world_ref::layer_norm(world_ref::to_vec(x), 6, 48, 1e-5, &w["ln.weight"], &w["ln.bias"]));
  plain(ctx(), x, x);  // in place
  expect_rel("layer norm (no affine, in place)", x,
             world_ref::layer_norm(world_ref::to_vec(world_ref::random_tensor({6, 48}, 4, -3.f, 5.f)), 6, 48, 1e-6,
                                   nullptr, nullptr));
}

TEST_CASE("MLPs: Sequential(0, GELU, 2) erf/tanh and MLPEmbedder(in_layer, SiLU, out_layer)") {
  world_ref::RandomWeights w(5);
  w.linear("mst.0.", 16, 64, false);
  w.linear("mst.2.", 64, 16, false);
  w.linear("dit.0.", 16, 64, true);
  w.linear("dit.2.", 64, 16, true);
  w.linear("emb.in_layer.", 16, 24, true);
  w.linear("emb.out_layer.", 24, 24, true);
  const auto x = world_ref::random_tensor({4, 16}, 6, -2.f, 2.f);
  const Vec xv = world_ref::to_vec(x);
  HostTensor hidden({4, 64}), y({4, 16});
  for (const auto gelu : {nn::Gelu::Erf, nn::Gelu::Tanh}) {
    const bool erf = gelu == nn::Gelu::Erf;
    const std::string p = erf ? "mst." : "dit.";
    nn::SequentialMlp<Cpu, float> mlp(16, 64, 16, !erf, gelu);
    bind_strict(mlp, w, p);
    mlp(ctx(), x, hidden, y);
    auto h = world_ref::linear(w, p + "0.", xv, 4, 16, 64, !erf);
    h = erf ? world_ref::map(h, world_ref::gelu_erf) : world_ref::map(h, world_ref::gelu_tanh);
    expect_rel(erf ? "MST MLP (erf)" : "DiT MLP (tanh)", y, world_ref::linear(w, p + "2.", h, 4, 64, 16, !erf));
  }
  nn::MlpEmbedder<Cpu, float> emb(16, 24);
  bind_strict(emb, w, "emb.");
  HostTensor eh({4, 24}), ey({4, 24});
  emb(ctx(), x, eh, ey);
  const auto h = world_ref::map(world_ref::linear(w, "emb.in_layer.", xv, 4, 16, 24, true), world_ref::silu);
  expect_rel("MLPEmbedder", ey, world_ref::linear(w, "emb.out_layer.", h, 4, 24, 24, true));
}

TEST_CASE("Modulation: Linear(SiLU(vec)) into the front of a larger buffer, chunks in order") {
  world_ref::RandomWeights w(7);
  w.linear("mod.lin.", 20, 60, true);
  nn::Modulation<Cpu, float> mod(20, 3);
  bind_strict(mod, w, "mod.lin.");
  const auto vec = world_ref::random_tensor({1, 20}, 8, -2.f, 2.f);
  HostTensor silu_vec({1, 20}), out = HostTensor::full({1, 120}, -7.f);
  for (i64 i = 0; i < 20; ++i) silu_vec.data()[i] = float(world_ref::silu(vec.data()[i]));
  mod(ctx(), silu_vec, out);
  const Vec ref = world_ref::linear(w, "mod.lin.", world_ref::map(world_ref::to_vec(vec), world_ref::silu), 1, 20, 60, true);
  expect_rel("modulation", out.reshape({120}).slice(0, 60), ref);
  CHECK(out.data()[60] == -7.f);  // nothing written past chunks·dim
  HostTensor small({1, 59});
  CHECK_THROWS_AS(mod(ctx(), silu_vec, small), Error);
}

TEST_CASE("QkNorm: per-head RMSNorm of q and k with their own scales") {
  world_ref::RandomWeights w(9);
  const i64 d = 128, heads = 2, rows = 5, stride = 3 * heads * d;
  w.add("n.query_norm.scale", {d}, 0.3, 1.0);
  w.add("n.key_norm.scale", {d}, 0.3, 1.0);
  nn::QkNorm<Cpu> norm(d, 1e-6f);
  bind_strict(norm, w, "n.");
  auto x = world_ref::random_tensor({rows, stride}, 10, -3.f, 3.f);
  Vec ref = world_ref::to_vec(x);
  world_ref::rms_heads(ref, rows, stride, 0, heads, d, w["n.query_norm.scale"], 1e-6);
  world_ref::rms_heads(ref, rows, stride, heads * d, heads, d, w["n.key_norm.scale"], 1e-6);
  norm(ctx(), x.data(), x.data() + heads * d, rows, stride, heads);
  expect_rel("QK RMSNorm", x, ref);
}

TEST_CASE("packed attention: MST time (causal across frames) and space layouts, head dims 128/64/24") {
  for (const i64 d : {128, 64, 24}) {
    const i64 F = 4, T = 9, H = 2, C = H * d;
    const auto q = world_ref::random_tensor({F * T, C}, 20 + d), k = world_ref::random_tensor({F * T, C}, 21 + d),
               v = world_ref::random_tensor({F * T, C}, 22 + d);
    HostTensor o({F * T, C});
    // time: T sequences (token positions) of F frames, causal
    nn::packed_attention(ctx(), q.data(), k.data(), v.data(), o.data(), {T, F, H, d, C, T * C, C, T * C, true});
    Vec ref(static_cast<std::size_t>(F * T * C));
    for (i64 l = 0; l < T; ++l) {
      Vec packed(static_cast<std::size_t>(F * 3 * C));
      for (i64 f = 0; f < F; ++f)
        for (i64 c = 0; c < C; ++c) {
          packed[f * 3 * C + c] = q.at(f * T + l, c);
          packed[f * 3 * C + C + c] = k.at(f * T + l, c);
          packed[f * 3 * C + 2 * C + c] = v.at(f * T + l, c);
        }
      const Vec out = world_ref::attention(packed, F, 3 * C, 0, C, 2 * C, H, d, true);
      for (i64 f = 0; f < F; ++f)
        for (i64 c = 0; c < C; ++c) ref[(f * T + l) * C + c] = out[f * C + c];
    }
    expect_rel(d == 128 ? "time attention d=128" : d == 64 ? "time attention d=64" : "time attention d=24", o, ref);
    // space: F sequences (frames) of T tokens, unmasked
    nn::packed_attention(ctx(), q.data(), k.data(), v.data(), o.data(), {F, T, H, d, T * C, C, T * C, C, false});
    for (i64 f = 0; f < F; ++f) {
      Vec packed(static_cast<std::size_t>(T * 3 * C));
      for (i64 t = 0; t < T; ++t)
        for (i64 c = 0; c < C; ++c) {
          packed[t * 3 * C + c] = q.at(f * T + t, c);
          packed[t * 3 * C + C + c] = k.at(f * T + t, c);
          packed[t * 3 * C + 2 * C + c] = v.at(f * T + t, c);
        }
      const Vec out = world_ref::attention(packed, T, 3 * C, 0, C, 2 * C, H, d, false);
      std::copy(out.begin(), out.end(), ref.begin() + f * T * C);
    }
    expect_rel(d == 128 ? "space attention d=128" : d == 64 ? "space attention d=64" : "space attention d=24", o, ref);
  }
}
