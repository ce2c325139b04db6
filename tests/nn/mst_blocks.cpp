// The MST (projectors, token assembly + time_emb, CausalTimeSpaceBlocks with causal time
// attention and space attention with the axial RoPE on image tokens only, evaluate's two
// outputs, get_pose_emb) at head dim 128 (the real one; the golden set has 64) against a
// float64 implementation written from world-model.md §3.9 and §5. Tolerance rel <= 1e-4;
// arena use must equal the planned bytes.
#include <array>
#include <doctest/doctest.h>

#include <string>

#include "epona/model/mst.hpp"
#include "world_reference.hpp"

using namespace epona;
using world_ref::HostTensor;
using world_ref::i64;
using world_ref::RandomWeights;
using world_ref::Vec;

namespace {

model::MstConfig small_config() {
  model::MstConfig c;
  c.n_embd = 256;
  c.n_head = 2;  // head dim 128
  c.n_layer = 2;
  c.condition_frames = 3;
  c.latent_h = 2;
  c.latent_w = 3;
  c.token_dim = 4;
  return c;
}

struct RefMst {
  const RandomWeights& w;
  const model::MstConfig& c;
  i64 C = c.n_embd, H = c.n_head, d = c.n_embd / c.n_head, T = 3 + c.latent_h * c.latent_w;

  Vec ln(const std::string& p, const Vec& x, i64 n) const {
    return world_ref::layer_norm(x, n, C, 1e-5, &w[p + "weight"], &w[p + "bias"]);
  }
  Vec projector(const std::string& p, const Vec& x, i64 n, i64 in, i64 hidden) const {
    const Vec h = world_ref::map(world_ref::linear(w, p + "0.", x, n, in, hidden, false), world_ref::gelu_erf);
    return ln(p + "3.", world_ref::linear(w, p + "2.", h, n, hidden, C, false), n);
  }
  // One pre-LN layer over a sequence of n tokens (n, C); rotate: image-token RoPE or none.
  void layer(const std::string& p, Vec& x, i64 n, bool causal, bool rotate) const {
    const Vec u = ln(p + "ln1.", x, n);
    const Vec q = ln(p + "attn.q_norm.", world_ref::linear(w, p + "attn.query.", u, n, C, C, false), n);
    const Vec k = ln(p + "attn.k_norm.", world_ref::linear(w, p + "attn.key.", u, n, C, C, false), n);
    const Vec v = world_ref::linear(w, p + "attn.value.", u, n, C, C, false);
    Vec packed(static_cast<std::size_t>(n * 3 * C));
    for (i64 r = 0; r < n; ++r) {
      std::copy_n(&q[r * C], C, &packed[r * 3 * C]);
      std::copy_n(&k[r * C], C, &packed[r * 3 * C + C]);
      std::copy_n(&v[r * C], C, &packed[r * 3 * C + 2 * C]);
    }
    if (rotate) {  // tokens 3.. : t' = t - 3, x = t' % h, y = t' // h
      std::vector<Vec> angle(static_cast<std::size_t>(n - 3), Vec(d / 2));
      for (i64 t = 0; t < n - 3; ++t)
        for (i64 j = 0; j < d / 4; ++j) {
          const double f = 1.0 / std::pow(1000.0, 4.0 * j / d);
          angle[t][j] = double(t % c.latent_h) * f;
          angle[t][d / 4 + j] = double(t / c.latent_h) * f;
        }
      Vec img(packed.begin() + 3 * 3 * C, packed.end());
      world_ref::rope(img, n - 3, 3 * C, 0, H, d, angle);
      world_ref::rope(img, n - 3, 3 * C, C, H, d, angle);
      std::copy(img.begin(), img.end(), packed.begin() + 3 * 3 * C);
    }
    const Vec o = world_ref::attention(packed, n, 3 * C, 0, C, 2 * C, H, d, causal);
    const Vec a = world_ref::linear(w, p + "attn.proj.", o, n, C, C, false);
    for (std::size_t i = 0; i < x.size(); ++i) x[i] += a[i];
    const Vec h = world_ref::map(world_ref::linear(w, p + "mlp.0.", ln(p + "ln2.", x, n), n, C, 4 * C, false),
                                 world_ref::gelu_erf);
    const Vec m = world_ref::linear(w, p + "mlp.2.", h, n, 4 * C, C, false);
    for (std::size_t i = 0; i < x.size(); ++i) x[i] += m[i];
  }

  // Projected actions of n entries, slots [yaw, pose_x, pose_y], each (n, C).
  std::vector<Vec> actions(const HostTensor& pose_idx, const HostTensor& yaw_idx, i64 n) const {
    Vec cy, cx, cz;
    for (i64 i = 0; i < n; ++i) {
      cy.push_back(double(yaw_idx.at(i, 0) / float(c.yaw_vocab)));
      cx.push_back(double(pose_idx.at(i, 0) / float(c.x_vocab)));
      cz.push_back(double(pose_idx.at(i, 1) / float(c.y_vocab)));
    }
    const i64 E = c.fourier_dim, P = c.projector_hidden;
    return {projector("yaw_projector.", world_ref::fourier(cy, E, 100), n, E, P),
            projector("pose_x_projector.", world_ref::fourier(cx, E, 100), n, E, P),
            projector("pose_y_projector.", world_ref::fourier(cz, E, 100), n, E, P)};
  }

  // evaluate for one batch item: (stt (T, C), pose_emb (3C)).
  std::pair<Vec, Vec> evaluate(const HostTensor& latents, const HostTensor& pose_idx, const HostTensor& yaw_idx) const {
    const i64 F = c.condition_frames, L = T - 3;
    const auto act = actions(pose_idx, yaw_idx, F + 1);
    const Vec img = projector("img_projector.", world_ref::to_vec(latents), F * L, c.token_dim, C / 2);
    Vec X(static_cast<std::size_t>(F * T * C));
    for (i64 f = 0; f < F; ++f)
      for (i64 t = 0; t < T; ++t)
        for (i64 i = 0; i < C; ++i)
          X[(f * T + t) * C + i] = (t < 3 ? act[t][f * C + i] : img[(f * L + t - 3) * C + i]) + w["time_emb"][f * C + i];
    for (i64 b = 0; b < c.n_layer; ++b) {
      const std::string p = "causal_time_space_blocks." + std::to_string(b) + ".";
      for (i64 t = 0; t < T; ++t) {  // time: the F frames of token position t, causal
        Vec seq(static_cast<std::size_t>(F * C));
        for (i64 f = 0; f < F; ++f) std::copy_n(&X[(f * T + t) * C], C, &seq[f * C]);
        layer(p + "causal_time_block.", seq, F, true, false);
        for (i64 f = 0; f < F; ++f) std::copy_n(&seq[f * C], C, &X[(f * T + t) * C]);
      }
      for (i64 f = 0; f < F; ++f) {  // space: the T tokens of frame f, unmasked, RoPE on image tokens
        Vec seq(X.begin() + f * T * C, X.begin() + (f + 1) * T * C);
        layer(p + "space_block.", seq, T, false, true);
        std::copy(seq.begin(), seq.end(), X.begin() + f * T * C);
      }
    }
    Vec pose_emb;
    for (const int slot : {1, 2, 0}) pose_emb.insert(pose_emb.end(), act[slot].begin() + F * C, act[slot].begin() + (F + 1) * C);
    return {Vec(X.begin() + (F - 1) * T * C, X.end()), pose_emb};
  }
};

// Entry e of every item's (B, entries, k) indices, as the (B, 1, k) that get_pose_emb takes.
HostTensor entry_of(const HostTensor& idx, i64 e) {
  HostTensor out({idx.size(0), 1, idx.size(2)});
  for (i64 b = 0; b < idx.size(0); ++b)
    for (i64 j = 0; j < idx.size(2); ++j) out.at(b, 0, j) = idx.at(b, e, j);
  return out;
}

// Binds every parameter of `mst` to w's random values (w keeps them for a reference).
void bind_random(model::SpatialTemporalTransformer<Cpu, float>& mst, RandomWeights& w) {
  w.add_all(mst.parameters());
  io::BindReport report(w.map());
  mst.bind(w.map(), "", report);
  report.finish(true);
}

}  // namespace

TEST_CASE("MST evaluate and get_pose_emb at head dim 128 vs float64") {
  const auto c = small_config();
  RandomWeights w(303);
  model::SpatialTemporalTransformer<Cpu, float> mst(c);
  bind_random(mst, w);

  const i64 B = 2, F = c.condition_frames, T = c.tokens_per_frame(), C = c.n_embd;
  const auto latents = world_ref::random_tensor({B, F, c.img_tokens(), c.token_dim}, 5, -2.f, 2.f);
  const auto pose_idx = world_ref::random_tensor({B, F + 1, 2}, 6, 0.f, 128.f);
  const auto yaw_idx = world_ref::random_tensor({B, F + 1, 1}, 7, 200.f, 300.f);
  HostTensor stt({B, T, C}), pose_emb({B, 3 * C});
  cpu::Context ctx(2);
  Arena<Cpu> arena(mst.evaluate_workspace_bytes(B));
  mst.evaluate(ctx, arena, latents, pose_idx, yaw_idx, stt, pose_emb);
  CHECK(arena.high_water() == mst.evaluate_workspace_bytes(B));

  // With an observer every frame of every block is computed; the last frame must not differ
  // from the pruned run beyond accumulation order.
  HostTensor stt_full({B, T, C}), emb_full({B, 3 * C});
  arena.reset();
  mst.evaluate(ctx, arena, latents, pose_idx, yaw_idx, stt_full, emb_full, [](auto, const auto&, const auto&) {});
  const double rel_pruned = world_ref::rel_max(stt, world_ref::to_vec(stt_full));
  MESSAGE("pruned last block vs full: rel ", rel_pruned);
  CHECK(rel_pruned <= 1e-6);

  const RefMst ref{w, c};
  for (i64 b = 0; b < B; ++b) {
    const auto [stt_ref, emb_ref] = ref.evaluate(latents[b], pose_idx[b], yaw_idx[b]);
    const double rel_stt = world_ref::rel_max(stt[b], stt_ref), rel_emb = world_ref::rel_max(pose_emb[b], emb_ref);
    MESSAGE("MST head dim 128, item ", b, ": stt_features rel ", rel_stt, ", pose_emb rel ", rel_emb);
    CHECK(rel_stt <= 1e-4);
    CHECK(rel_emb <= 1e-4);
  }

  // get_pose_emb of entry F alone equals evaluate's pose_emb (up to GEMM accumulation order).
  HostTensor emb({B, 3 * C});
  Arena<Cpu> small(mst.pose_emb_workspace_bytes(B));
  mst.get_pose_emb(ctx, small, entry_of(pose_idx, F), entry_of(yaw_idx, F), emb);
  const double rel = world_ref::rel_max(emb, world_ref::to_vec(pose_emb));
  MESSAGE("get_pose_emb vs evaluate's pose_emb: rel ", rel);
  CHECK(rel <= 1e-5);
}

TEST_CASE("MST folds a batch into its rows: each item as evaluated alone") {
  // kMaxFoldedItems + 2 windows: a folded pass of 8 and one of 2, frame-major. Each item's
  // stt_features and pose_emb must be what it gives alone, as must get_pose_emb of the batch.
  const auto c = small_config();
  RandomWeights w(404);
  model::SpatialTemporalTransformer<Cpu, float> mst(c);
  bind_random(mst, w);
  const i64 B = model::SpatialTemporalTransformer<Cpu, float>::kMaxFoldedItems + 2, F = c.condition_frames;
  const i64 T = c.tokens_per_frame(), C = c.n_embd;
  const auto latents = world_ref::random_tensor({B, F, c.img_tokens(), c.token_dim}, 15, -2.f, 2.f);
  const auto pose_idx = world_ref::random_tensor({B, F + 1, 2}, 16, 0.f, 128.f);
  const auto yaw_idx = world_ref::random_tensor({B, F + 1, 1}, 17, 200.f, 300.f);
  cpu::Context ctx(2);
  const auto run = [&](const HostTensor& lat, const HostTensor& pose, const HostTensor& yaw) {
    const i64 n = lat.size(0);
    HostTensor stt({n, T, C}), emb({n, 3 * C}), one_emb({n, 3 * C});
    Arena<Cpu> arena(std::max(mst.evaluate_workspace_bytes(n), mst.pose_emb_workspace_bytes(n)));
    mst.evaluate(ctx, arena, lat, pose, yaw, stt, emb);
    CHECK(arena.high_water() == mst.evaluate_workspace_bytes(n));
    arena.reset();
    mst.get_pose_emb(ctx, arena, entry_of(pose, F), entry_of(yaw, F), one_emb);
    return std::array<HostTensor, 3>{stt, emb, one_emb};
  };
  const auto one = [](const HostTensor& t, i64 b) {
    Shape s = t.shape();
    s[0] = 1;
    return t.slice(b, b + 1).clone().reshape(s);
  };
  const auto batched = run(latents, pose_idx, yaw_idx);
  double worst[3] = {0, 0, 0};
  for (i64 b = 0; b < B; ++b) {
    const auto alone = run(one(latents, b), one(pose_idx, b), one(yaw_idx, b));
    for (int k = 0; k < 3; ++k)
      worst[k] = std::max(worst[k], world_ref::rel_max(one(batched[k], b), world_ref::to_vec(alone[k])));
  }
  MESSAGE("MST batch of ", B, " vs each item alone: stt_features rel ", worst[0], ", pose_emb ", worst[1],
          ", get_pose_emb ", worst[2]);
  for (const double rel : worst) CHECK(rel <= 1e-6);
  CHECK(world_ref::rel_max(one(batched[0], 0), world_ref::to_vec(one(batched[0], 1))) > 1e-2);

  // Passes of 3 (3, 3, 3, 1): the arena follows the limit, and the items are the same.
  mst.set_fold_limit(3);
  CHECK(mst.evaluate_workspace_bytes(B) < mst.evaluate_workspace_bytes(1) * 4);
  const auto by_three = run(latents, pose_idx, yaw_idx);
  const double rel3 = world_ref::rel_max(by_three[0], world_ref::to_vec(batched[0]));
  MESSAGE("MST batch of ", B, " in passes of 3 vs passes of 8: stt_features rel ", rel3);
  CHECK(rel3 <= 1e-6);
  CHECK_THROWS_WITH_AS(mst.set_fold_limit(0), doctest::Contains("windows per pass"), Error);
  CHECK_THROWS_WITH_AS(mst.set_fold_limit(model::SpatialTemporalTransformer<Cpu, float>::kMaxFoldedItems + 1),
                       doctest::Contains("windows per pass"), Error);
  CHECK(mst.fold_limit() == 3);
}

TEST_CASE("MST input shapes are checked") {
  const auto c = small_config();
  model::SpatialTemporalTransformer<Cpu, float> mst(c);
  cpu::Context ctx(1);
  Arena<Cpu> arena(mst.evaluate_workspace_bytes());
  HostTensor latents({1, c.condition_frames + 1, c.img_tokens(), c.token_dim}), pose({1, c.condition_frames + 1, 2}),
      yaw({1, c.condition_frames + 1, 1}), stt({1, c.tokens_per_frame(), c.n_embd}), emb({1, 3 * c.n_embd});
  CHECK_THROWS_WITH_AS(mst.evaluate(ctx, arena, latents, pose, yaw, stt, emb), doctest::Contains("MST latents"), Error);
}
