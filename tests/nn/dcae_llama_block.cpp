// Tests for epona/nn/blocks/llama_block.hpp (the temporal decoder's TransformerBlock) against a float64
// loop written from spec §6.3-§6.4: RMSNorm (weight only, eps 1e-5), q/k/v, 1-D RoPE (theta 1000,
// adjacent pairs) at each token's position, softmax(q·k/sqrt(4)) with or without the causal
// mask, wo, + x, RMSNorm, SwiGLU (w2(silu(w1 h) * w3 h)), + x. Both strided layouts (time:
// sequences across frames; space: sequences across tokens), causality, the F = 1 reduction, and
// the RoPE positions. Tolerance rel <= 2e-6.
#include <doctest/doctest.h>

#include "dcae_reference.hpp"
#include "epona/nn/blocks/llama_block.hpp"

using namespace epona;
using dcae_ref::HostTensor;
using dcae_ref::i64;
using dcae_ref::Vec;

namespace {

constexpr i64 D = 32, kHeads = 8, kHidden = 256;

nn::TransformerBlock<Cpu, float> make_block(std::uint64_t seed) {
  nn::TransformerBlock<Cpu, float> b(D, kHeads, kHidden, 1e-5f, 1000.f);
  b.randomize(seed);
  return b;
}

Vec matvec(const HostTensor& w, const Vec& x) {  // w (out, in) · x
  Vec y(static_cast<std::size_t>(w.size(0)), 0.0);
  for (i64 o = 0; o < w.size(0); ++o)
    for (i64 i = 0; i < w.size(1); ++i) y[o] += double(w.at(o, i)) * x[i];
  return y;
}

Vec rms(const Vec& x, const HostTensor& w) {
  double ss = 0;
  for (double v : x) ss += v * v;
  const double r = 1.0 / std::sqrt(ss / double(x.size()) + 1e-5);
  Vec y(x.size());
  for (std::size_t i = 0; i < x.size(); ++i) y[i] = x[i] * r * w.data()[i];
  return y;
}

void rope(Vec& v, i64 pos) {
  const i64 hd = D / kHeads;
  for (i64 h = 0; h < kHeads; ++h)
    for (i64 j = 0; j < hd / 2; ++j) {
      const double theta = double(pos) * std::pow(1000.0, -2.0 * double(j) / double(hd));
      double& a = v[h * hd + 2 * j];
      double& b = v[h * hd + 2 * j + 1];
      const double a0 = a, b0 = b;
      a = a0 * std::cos(theta) - b0 * std::sin(theta);
      b = a0 * std::sin(theta) + b0 * std::cos(theta);
    }
}

// The block over explicit sequences: seqs[s][t] = row of token t (position t).
Vec block_ref(const nn::TransformerBlock<Cpu, float>& b, const HostTensor& x,
              const std::vector<std::vector<i64>>& seqs, bool causal) {
  const i64 hd = D / kHeads;
  Vec out(dcae_ref::to_vec(x));
  auto row = [&](const Vec& m, i64 r) { return Vec(m.begin() + r * D, m.begin() + (r + 1) * D); };
  const Vec x0 = dcae_ref::to_vec(x);
  for (const auto& seq : seqs) {
    const i64 T = static_cast<i64>(seq.size());
    std::vector<Vec> q(T), k(T), v(T);
    for (i64 t = 0; t < T; ++t) {
      const Vec h = rms(row(x0, seq[t]), b.attention_norm);
      q[t] = matvec(b.wq, h), k[t] = matvec(b.wk, h), v[t] = matvec(b.wv, h);
      rope(q[t], t), rope(k[t], t);
    }
    for (i64 t = 0; t < T; ++t) {
      Vec o(D, 0.0);
      for (i64 h = 0; h < kHeads; ++h) {
        const i64 nk = causal ? t + 1 : T;
        Vec s(static_cast<std::size_t>(nk));
        double mx = -INFINITY, den = 0;
        for (i64 u = 0; u < nk; ++u) {
          double dot = 0;
          for (i64 e = 0; e < hd; ++e) dot += q[t][h * hd + e] * k[u][h * hd + e];
          s[u] = dot / std::sqrt(double(hd));
          mx = std::max(mx, s[u]);
        }
        for (auto& e : s) den += (e = std::exp(e - mx));
        for (i64 u = 0; u < nk; ++u)
          for (i64 e = 0; e < hd; ++e) o[h * hd + e] += s[u] / den * v[u][h * hd + e];
      }
      Vec x1 = row(x0, seq[t]);
      const Vec proj = matvec(b.wo, o);
      for (i64 c = 0; c < D; ++c) x1[c] += proj[c];
      const Vec h2 = rms(x1, b.ffn_norm);
      const Vec g = matvec(b.w1, h2), val = matvec(b.w3, h2);
      Vec mid(static_cast<std::size_t>(kHidden));
      for (i64 i = 0; i < kHidden; ++i) mid[i] = dcae_ref::silu(g[i]) * val[i];
      const Vec ffn = matvec(b.w2, mid);
      for (i64 c = 0; c < D; ++c) out[seq[t] * D + c] = x1[c] + ffn[c];
    }
  }
  return out;
}

// Sequences of a (clips, F, L) token grid: time = across frames per token, space = across tokens.
std::vector<std::vector<i64>> grid_sequences(i64 clips, i64 F, i64 L, bool time) {
  std::vector<std::vector<i64>> seqs;
  for (i64 b = 0; b < clips; ++b)
    for (i64 outer = 0; outer < (time ? L : F); ++outer) {
      std::vector<i64> s;
      for (i64 t = 0; t < (time ? F : L); ++t) s.push_back(b * F * L + (time ? t * L + outer : outer * L + t));
      seqs.push_back(s);
    }
  return seqs;
}

HostTensor run(const nn::TransformerBlock<Cpu, float>& b, HostTensor x, const nn::TokenSequences& seq) {
  cpu::Context ctx;
  std::vector<float> c, s;
  nn::rope_table_1d(seq, b.head_dim(), b.rope_theta, c, s);
  b.forward_inplace(ctx, x, seq, c.data(), s.data());
  return x;
}

}  // namespace

TEST_CASE("time block: causal attention across the frames of each token, RoPE position = frame") {
  const i64 clips = 2, F = 3, L = 5;
  const auto block = make_block(1);
  const HostTensor x = dcae_ref::random_tensor({clips * F * L, D}, 2, -2.f, 2.f);
  const nn::TokenSequences time{clips, L, F, 1, L, true};
  CHECK(dcae_ref::rel_max(run(block, x, time), block_ref(block, x, grid_sequences(clips, F, L, true), true)) <= 2e-6);
}

TEST_CASE("space block: full attention across the tokens of each frame, RoPE position = token index") {
  const i64 clips = 2, F = 3, L = 7;
  const auto block = make_block(3);
  const HostTensor x = dcae_ref::random_tensor({clips * F * L, D}, 4, -2.f, 2.f);
  const nn::TokenSequences space{clips, F, L, L, 1, false};
  CHECK(dcae_ref::rel_max(run(block, x, space), block_ref(block, x, grid_sequences(clips, F, L, false), false)) <=
        2e-6);
}

TEST_CASE("causal time attention: later frames never change earlier outputs") {
  const i64 clips = 1, F = 4, L = 3;
  const auto block = make_block(5);
  const nn::TokenSequences time{clips, L, F, 1, L, true};
  HostTensor x = dcae_ref::random_tensor({F * L, D}, 6);
  const HostTensor before = run(block, x, time);
  for (i64 i = 2 * L * D; i < F * L * D; ++i) x.data()[i] += 1.f;  // frames 2 and 3
  const HostTensor after = run(block, x, time);
  for (i64 i = 0; i < 2 * L * D; ++i) CHECK(after.data()[i] == before.data()[i]);
}

TEST_CASE("one frame: the time block's attention is x + Wo·Wv·RMSNorm(x), then the FFN") {
  const i64 L = 4;
  const auto block = make_block(7);
  HostTensor x = dcae_ref::random_tensor({2 * L, D}, 8);
  const nn::TokenSequences time{2, L, 1, 1, L, true};
  std::vector<std::vector<i64>> singles;
  for (i64 r = 0; r < 2 * L; ++r) singles.push_back({r});
  CHECK(dcae_ref::rel_max(run(block, x, time), block_ref(block, x, singles, true)) <= 2e-6);
}

TEST_CASE("RoPE table: positions of both layouts, float32 frequencies 1000^(-2j/4)") {
  const nn::TokenSequences time{2, 5, 3, 1, 5, true}, space{2, 3, 5, 5, 1, false};
  for (i64 r = 0; r < time.rows(); ++r) {
    CHECK(time.position(r) == (r % 15) / 5);
    CHECK(space.position(r) == r % 5);
  }
  std::vector<float> c, s;
  nn::rope_table_1d(space, 4, 1000.f, c, s);
  const i64 r = 13;  // position 3
  CHECK(c[r * 2] == doctest::Approx(std::cos(3.0)).epsilon(1e-6));
  CHECK(s[r * 2 + 1] == doctest::Approx(std::sin(3.0 / std::sqrt(1000.0))).epsilon(1e-6));
}
