// Tests for epona/cpu/attention.hpp: the tiled online-softmax attention against a float64
// loop that materialises every score, for full / causal / additive masks, head dims 4..128
// (compiled-in and run-time), lq != lk, tiles with tails, the packed-QKV layout, the MST's
// time-attention strides (seq stride C, row stride T·C) and fully masked rows (zeros).
// Tolerance: max |got − ref| / max |ref| <= 1e-5 over each output.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>

#include "epona/core/error.hpp"
#include "epona/cpu/attention.hpp"
#include "testing.hpp"

using namespace epona;
using cpu::AttentionShape;

namespace {
constexpr float kNegInf = -std::numeric_limits<float>::infinity();

// Output (s, i, h, :) of the float64 reference; same strides as the kernel sees.
std::vector<double> attention_ref(const float* q, const float* k, const float* v, const AttentionShape& a,
                                  std::size_t out_size) {
  std::vector<double> o(out_size, 0.0);
  const std::int64_t D = a.head_dim;
  const double scale = a.scale != 0 ? a.scale : 1.0f / std::sqrt(static_cast<float>(D));
  std::vector<double> sc(static_cast<std::size_t>(a.lk));
  for (std::int64_t s = 0; s < a.seqs; ++s)
    for (std::int64_t h = 0; h < a.heads; ++h)
      for (std::int64_t i = 0; i < a.lq; ++i) {
        double mx = -INFINITY;
        for (std::int64_t j = 0; j < a.lk; ++j) {
          double dot = 0;
          for (std::int64_t d = 0; d < D; ++d)
            dot += double(q[s * a.q_seq + i * a.q_row + h * D + d]) * k[s * a.k_seq + j * a.k_row + h * D + d];
          sc[j] = dot * scale + (a.additive_mask ? a.additive_mask[i * a.lk + j] : 0.0);
          if (a.mask == cpu::Mask::Causal && j > i) sc[j] = -INFINITY;
          mx = std::max(mx, sc[j]);
        }
        if (mx == -INFINITY) continue;  // fully masked: zeros
        double den = 0;
        for (std::int64_t j = 0; j < a.lk; ++j) den += (sc[j] = std::exp(sc[j] - mx));
        for (std::int64_t d = 0; d < D; ++d) {
          double acc = 0;
          for (std::int64_t j = 0; j < a.lk; ++j) acc += sc[j] * v[s * a.v_seq + j * a.v_row + h * D + d];
          o[s * a.o_seq + i * a.o_row + h * D + d] = acc / den;
        }
      }
  return o;
}

// Contiguous (seqs, L, heads·D) buffers for q, k, v and o.
struct Contiguous {
  std::vector<float> q, k, v, o;
  AttentionShape a;
  Contiguous(std::int64_t seqs, std::int64_t heads, std::int64_t lq, std::int64_t lk, std::int64_t D,
             std::uint32_t seed, float amp = 1.f) {
    const std::int64_t C = heads * D;
    q = test::random_floats(static_cast<std::size_t>(seqs * lq * C), seed, -amp, amp);
    k = test::random_floats(static_cast<std::size_t>(seqs * lk * C), seed + 1, -amp, amp);
    v = test::random_floats(static_cast<std::size_t>(seqs * lk * C), seed + 2);
    o.assign(static_cast<std::size_t>(seqs * lq * C), 123.f);
    a.seqs = seqs, a.heads = heads, a.lq = lq, a.lk = lk, a.head_dim = D;
    a.q_seq = a.o_seq = lq * C;
    a.k_seq = a.v_seq = lk * C;
    a.q_row = a.k_row = a.v_row = a.o_row = C;
  }
  double run() {
    cpu::Context ctx;
    cpu::attention(ctx, q.data(), k.data(), v.data(), o.data(), a);
    return test::rel_max(o, attention_ref(q.data(), k.data(), v.data(), a, o.size()));
  }
};
}  // namespace

TEST_CASE("attention, full and causal, head dims 4..128, tails of query and key tiles") {
  for (std::int64_t D : {4, 13, 24, 32, 64, 128})
    for (auto [lq, lk] : {std::pair<std::int64_t, std::int64_t>{1, 1}, {5, 5}, {37, 37}, {70, 131}, {131, 70},
                          {33, 200}})
      for (auto mask : {cpu::Mask::None, cpu::Mask::Causal}) {
        Contiguous c(2, 3, lq, lk, D, static_cast<std::uint32_t>(D * 1000 + lq), 2.f);
        c.a.mask = mask;
        CAPTURE(D);
        CAPTURE(lq);
        CAPTURE(lk);
        CAPTURE(static_cast<int>(mask));
        CHECK(c.run() <= 1e-5);
      }
}

TEST_CASE("attention with an explicit scale and an additive mask, including fully masked rows") {
  for (std::int64_t D : {24, 128}) {
    const std::int64_t lq = 45, lk = 77;
    Contiguous c(2, 2, lq, lk, D, 900, 1.5f);
    auto mask = test::random_floats(static_cast<std::size_t>(lq * lk), 901, -3.f, 3.f);
    for (std::int64_t i = 0; i < lq; ++i)
      for (std::int64_t j = 0; j < lk; ++j) {
        if ((i * 7 + j) % 5 == 0) mask[i * lk + j] = kNegInf;  // scattered −inf
        if (i == 3 || i == 40) mask[i * lk + j] = kNegInf;     // rows that see nothing
        if (i == 10 && j < 70) mask[i * lk + j] = kNegInf;     // only the last key tile
      }
    c.a.additive_mask = mask.data();
    c.a.scale = 0.3f;
    CAPTURE(D);
    CHECK(c.run() <= 1e-5);
    for (std::int64_t s = 0; s < 2; ++s)
      for (std::int64_t i : {3, 40})
        for (std::int64_t x = 0; x < 2 * D; ++x) CHECK(c.o[s * c.a.o_seq + i * c.a.o_row + x] == 0.f);
    for (float x : c.o) CHECK(std::isfinite(x));
    // Causal combined with the additive mask.
    c.a.mask = cpu::Mask::Causal;
    CHECK(c.run() <= 1e-5);
  }
}

TEST_CASE("attention with causal lq > lk and a fully masked first query") {
  Contiguous c(1, 2, 40, 20, 32, 950);
  c.a.mask = cpu::Mask::Causal;
  CHECK(c.run() <= 1e-5);
  std::vector<float> mask(40 * 20, 0.f);
  for (std::int64_t j = 0; j < 20; ++j) mask[j] = kNegInf;  // query 0 sees only key 0, masked here
  c.a.additive_mask = mask.data();
  CHECK(c.run() <= 1e-5);
  for (std::int64_t x = 0; x < 64; ++x) CHECK(c.o[x] == 0.f);
}

TEST_CASE("attention with no keys gives zeros") {
  Contiguous c(2, 2, 5, 0, 24, 960);
  CHECK(c.run() <= 1e-5);
  for (float x : c.o) CHECK(x == 0.f);
}

TEST_CASE("attention straight out of a packed QKV buffer") {
  // x: (seqs, L, 3·C) with q | k | v side by side per token; o: (seqs, L, C).
  for (std::int64_t D : {24, 128}) {
    const std::int64_t seqs = 2, heads = 3, L = 67, C = heads * D;
    const auto qkv = test::random_floats(static_cast<std::size_t>(seqs * L * 3 * C), 77, -2.f, 2.f);
    std::vector<float> o(static_cast<std::size_t>(seqs * L * C));
    AttentionShape a;
    a.seqs = seqs, a.heads = heads, a.lq = a.lk = L, a.head_dim = D;
    a.q_seq = a.k_seq = a.v_seq = L * 3 * C;
    a.q_row = a.k_row = a.v_row = 3 * C;
    a.o_seq = L * C, a.o_row = C;
    cpu::Context ctx;
    cpu::attention(ctx, qkv.data(), qkv.data() + C, qkv.data() + 2 * C, o.data(), a);
    CAPTURE(D);
    CHECK(test::rel_max(o, attention_ref(qkv.data(), qkv.data() + C, qkv.data() + 2 * C, a, o.size())) <= 1e-5);
  }
}

TEST_CASE("attention with the MST time-attention strides (sequences are tokens, rows are frames)") {
  // Activations (frames, T, C): token t of frame f at (f·T + t)·C. Sequence = token (stride C),
  // row = frame (stride T·C); causal over frames, as M_time.
  const std::int64_t frames = 10, T = 19, heads = 2, D = 128, C = heads * D;
  const auto q = test::random_floats(static_cast<std::size_t>(frames * T * C), 81, -2.f, 2.f);
  const auto k = test::random_floats(q.size(), 82, -2.f, 2.f);
  const auto v = test::random_floats(q.size(), 83);
  for (bool additive : {false, true}) {
    std::vector<float> o(q.size(), 7.f);
    std::vector<float> m_time(frames * frames, 0.f);
    for (std::int64_t i = 0; i < frames; ++i)
      for (std::int64_t j = i + 1; j < frames; ++j) m_time[i * frames + j] = kNegInf;
    AttentionShape a;
    a.seqs = T, a.heads = heads, a.lq = a.lk = frames, a.head_dim = D;
    a.q_seq = a.k_seq = a.v_seq = a.o_seq = C;
    a.q_row = a.k_row = a.v_row = a.o_row = T * C;
    if (additive) a.additive_mask = m_time.data();
    else a.mask = cpu::Mask::Causal;
    cpu::Context ctx;
    cpu::attention(ctx, q.data(), k.data(), v.data(), o.data(), a);
    CAPTURE(additive);
    CHECK(test::rel_max(o, attention_ref(q.data(), k.data(), v.data(), a, o.size())) <= 1e-5);
  }
}

TEST_CASE("attention writes only its own heads of a wider output, and rejects bad shapes") {
  // o rows wider than heads·D: the extra columns must stay untouched.
  const std::int64_t seqs = 1, heads = 2, L = 9, D = 32, C = heads * D, ow = C + 11;
  Contiguous c(seqs, heads, L, L, D, 99);
  std::vector<float> o(static_cast<std::size_t>(L * ow), 5.f);
  c.a.o_seq = L * ow;
  c.a.o_row = ow;
  cpu::Context ctx;
  cpu::attention(ctx, c.q.data(), c.k.data(), c.v.data(), o.data(), c.a);
  auto ref = attention_ref(c.q.data(), c.k.data(), c.v.data(), c.a, o.size());
  for (std::int64_t i = 0; i < L; ++i)
    for (std::int64_t x = C; x < ow; ++x) {
      CHECK(o[i * ow + x] == 5.f);
      o[i * ow + x] = 0.f;  // the reference leaves these 0
    }
  CHECK(test::rel_max(o.data(), ref.data(), o.size()) <= 1e-5);
  c.a.head_dim = 0;
  CHECK_THROWS_WITH_AS(cpu::attention(ctx, c.q.data(), c.k.data(), c.v.data(), o.data(), c.a),
                       doctest::Contains("head_dim"), Error);
}
