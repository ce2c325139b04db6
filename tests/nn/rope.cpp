// RoPE tables and their application against float64 loops: the MST's axial table (token t at
// x = t % h, y = t // h — the official modulus — pairs [0, d/4) on x, [d/4, d/2) on y,
// frequencies 1000^(-4j/d)) and the DiTs' ND table (axis by axis, 10000^(-2m/a_i), float64
// angles), the real sizes included; rotation of packed q/k rows for head dims 128, 64, 24.
#include <doctest/doctest.h>

#include <cmath>

#include "epona/nn/rope.hpp"
#include "world_reference.hpp"

using namespace epona;
using world_ref::i64;
using world_ref::HostTensor;

namespace {
double max_table_error(const nn::RopeTable<Cpu>& t, const std::vector<world_ref::Vec>& angle) {
  double err = 0;
  for (i64 r = 0; r < t.rows(); ++r)
    for (i64 p = 0; p < t.pairs(); ++p) {
      err = std::max(err, std::abs(t.cos.at(r, p) - std::cos(angle[r][p])));
      err = std::max(err, std::abs(t.sin.at(r, p) - std::sin(angle[r][p])));
    }
  return err;
}
}  // namespace

TEST_CASE("MST axial table: x = t % h, y = t // h, theta 1000") {
  for (const auto& [d, h, w] : {std::tuple<i64, i64, i64>{128, 16, 32}, {64, 2, 4}, {8, 3, 5}}) {
    const auto t = nn::axial_rope_table(d, h, w, 1000.0f);
    REQUIRE(t.rows() == h * w);
    REQUIRE(t.pairs() == d / 2);
    std::vector<world_ref::Vec> angle(static_cast<std::size_t>(h * w), world_ref::Vec(d / 2));
    for (i64 tok = 0; tok < h * w; ++tok)
      for (i64 j = 0; j < d / 4; ++j) {
        const double freq = 1.0 / std::pow(1000.0, 4.0 * j / d);
        angle[tok][j] = double(tok % h) * freq;
        angle[tok][d / 4 + j] = double(tok / h) * freq;
      }
    // fp32 angles: |error| <= angle · 2^-23 (the largest angle is the row index, < 2w).
    const double err = max_table_error(t, angle);
    MESSAGE("axial d=", d, " h=", h, " w=", w, ": max |error| ", err);
    CHECK(err <= 1e-5);
  }
}

TEST_CASE("DiT ND table: axes laid out in order, float64 angles") {
  const std::vector<i64> axes{16, 56, 56};
  HostTensor ids({40, 3});
  for (i64 r = 0; r < 40; ++r) {
    ids.at(r, 0) = 0;
    ids.at(r, 1) = float(r / 8);
    ids.at(r, 2) = float(r % 32);
  }
  const auto t = nn::nd_rope_table(ids, axes, 10000.0);
  std::vector<world_ref::Vec> angle(40, world_ref::Vec(64));
  for (i64 r = 0; r < 40; ++r) {
    i64 p = 0;
    for (std::size_t a = 0; a < axes.size(); ++a)
      for (i64 m = 0; m < axes[a] / 2; ++m, ++p)
        angle[r][p] = double(ids.at(r, i64(a))) / std::pow(10000.0, 2.0 * m / double(axes[a]));
  }
  const double err = max_table_error(t, angle);
  MESSAGE("ND table: max |error| ", err);
  CHECK(err <= 6e-8);  // float64 values rounded once to float32
  for (i64 p = 0; p < 8; ++p) CHECK(t.cos.at(39, p) == 1.0f);  // axis 0 (always 0) never rotates
}

TEST_CASE("apply_rope_qk rotates interleaved pairs of every head of packed rows") {
  cpu::Context ctx(2);
  const std::vector<std::pair<i64, std::vector<i64>>> cases{{128, {16, 56, 56}}, {64, {4, 30, 30}}, {24, {4, 10, 10}}};
  for (const auto& [d, axes] : cases) {
    const i64 heads = 3, rows = 7, stride = 3 * heads * d;  // [q | k | v] rows
    HostTensor ids({rows, 3});
    for (i64 r = 0; r < rows; ++r) ids.at(r, 0) = 0, ids.at(r, 1) = float(r), ids.at(r, 2) = float(2 * r + 1);
    const auto table = nn::nd_rope_table(ids, axes, 10000.0);
    auto x = world_ref::random_tensor({rows, stride}, 11 + d);
    const auto before = x.clone();
    auto ref = world_ref::to_vec(x);
    std::vector<world_ref::Vec> angle(rows, world_ref::Vec(d / 2));
    for (i64 r = 0; r < rows; ++r)
      for (i64 p = 0; p < d / 2; ++p) angle[r][p] = std::atan2(table.sin.at(r, p), table.cos.at(r, p));
    world_ref::rope(ref, rows, stride, 0, heads, d, angle);
    world_ref::rope(ref, rows, stride, heads * d, heads, d, angle);
    nn::apply_rope_qk(ctx, x.data(), x.data() + heads * d, rows, stride, heads, table);
    const double rel = world_ref::rel_max(x, ref);
    MESSAGE("head dim ", d, ": rel ", rel);
    CHECK(rel <= 1e-6);
    for (i64 r = 0; r < rows; ++r)  // v is untouched
      for (i64 c = 2 * heads * d; c < stride; ++c) REQUIRE(x.at(r, c) == before.at(r, c));
  }
}

TEST_CASE("table builders refuse impossible sizes") {
  CHECK_THROWS_AS(nn::axial_rope_table(6, 2, 2, 1000.f), Error);
  HostTensor ids({2, 3});
  CHECK_THROWS_AS(nn::nd_rope_table(ids, {4, 5, 4}, 1e4), Error);
  CHECK_THROWS_AS(nn::nd_rope_table(ids, {4, 4}, 1e4), Error);
}
