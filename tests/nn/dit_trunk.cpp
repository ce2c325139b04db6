// nn::DitTrunk: its fused chaining (each block's last add writing the next block's first norm,
// the pruned last single block, the condition rows read in place) gives the target rows the
// blocks give when called one by one with their defaults (no fusion, every row updated, z holding
// the condition). The blocks themselves are checked against float64 in dit_blocks.cpp.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>

#include "epona/core/arena.hpp"
#include "epona/nn/blocks/dit_trunk.hpp"

using namespace epona;

namespace {

using Trunk = nn::DitTrunk<Cpu, float>;

double rel_max(const Tensor<float>& a, const Tensor<float>& b) {
  double diff = 0, ref = 0;
  for (std::int64_t i = 0; i < a.numel(); ++i) {
    diff = std::max(diff, std::abs(double(a.data()[i]) - double(b.data()[i])));
    ref = std::max(ref, std::abs(double(b.data()[i])));
  }
  return diff / ref;
}

// The blocks of `t` called one by one with their defaults over z (condition rows included).
Tensor<float> unfused(cpu::Context& ctx, const Trunk& t, Arena<Cpu>& arena, const Tensor<float>& z,
                      const nn::JointRows& rows, const nn::RopeTable<Cpu>& rope, const float* mods) {
  ArenaScope<Cpu> scope(arena);
  auto s = t.plan_scratch(arena, rows);
  std::copy_n(z.data(), z.numel(), s.z.data());
  for (const auto& b : t.double_blocks()) {
    b(ctx, t.queue(), s, rows, rope, mods);
    mods += b.modulation_width();
  }
  for (const auto& b : t.single_blocks()) {
    b(ctx, t.queue(), s, rows, rope, mods);
    mods += b.modulation_width();
  }
  Tensor<float> out({rows.target, t.out_channels()});
  t.final_layer()(ctx, s, rows, mods, out);
  return out;
}

Tensor<float> trunk_out(cpu::Context& ctx, const Trunk& t, Arena<Cpu>& arena, const Tensor<float>& z,
                        const nn::JointRows& rows, const nn::RopeTable<Cpu>& rope, const float* mods, bool cond_apart) {
  ArenaScope<Cpu> scope(arena);
  auto s = t.plan_scratch(arena, rows);
  std::copy_n(z.data(), z.numel(), s.z.data());
  nn::TrunkInputs<Cpu, float> in;
  if (cond_apart) {  // the condition rows only where `in` points; z's own are poison
    in.cond = z.data();
    std::fill_n(s.z.data(), rows.cond * t.widths().hidden, std::numeric_limits<float>::quiet_NaN());
  }
  Tensor<float> out({rows.target, t.out_channels()});
  t(ctx, s, rows, rope, mods, out, in);
  return out;
}

}  // namespace

TEST_CASE("the trunk's fused chaining equals its blocks called one by one") {
  cpu::Context ctx;
  Arena<Cpu> arena(32 << 20);
  const nn::DitWidths w{64, 4, 256};
  const nn::JointRows rows{9, 13};
  Tensor<float> ids({rows.total(), 1});
  for (std::int64_t i = 0; i < rows.total(); ++i) ids.data()[i] = float(i);
  const auto rope = nn::nd_rope_table(ids, {w.head_dim()}, 10000.0);
  for (auto [doubles, singles] : {std::pair{2, 2}, std::pair{2, 0}, std::pair{0, 2}, std::pair{1, 1}, std::pair{0, 0}}) {
    CAPTURE(doubles);
    CAPTURE(singles);
    Trunk t(w, doubles, singles, 5);
    t.randomize(17);
    nn::RandomValues values(23);
    const Tensor<float> z = values.operator()<float>("z", {rows.total(), w.hidden});
    Tensor<float> mods = values.operator()<float>("mods", {1, t.modulation_width()});
    for (std::int64_t i = 0; i < mods.numel(); ++i) mods.data()[i] *= 0.3f;  // adaLN vectors of O(0.1)
    const Tensor<float> ref = unfused(ctx, t, arena, z, rows, rope, mods.data());
    const Tensor<float> fused = trunk_out(ctx, t, arena, z, rows, rope, mods.data(), false);
    const Tensor<float> apart = trunk_out(ctx, t, arena, z, rows, rope, mods.data(), true);
    CHECK(rel_max(fused, ref) <= 1e-5);
    CHECK(rel_max(apart, ref) <= 1e-5);
  }
}

TEST_CASE("the trunk's parameter tree names the official keys and counts them") {
  const Trunk t(nn::DitWidths{32, 2, 128}, 1, 1, 3);
  const nn::ParamList list = t.parameters("dit.");
  CHECK(list.entries().front().name == "dit.double_blocks.0.img_mod.lin.weight");
  CHECK(list.entries().back().name == "dit.final_layer.linear.bias");
  // Per double block 2 x (mod 6D(D+1), qkv 3D(D+1), proj D(D+1), mlp 4D(D+1) + D(4D+1), norms 2·16);
  // per single block linear1 7D(D+1), linear2 D(5D+1), norms 2·16, modulation 3D(D+1); final 2D(D+1) + 3(D+1).
  const double D = 32;
  const double dbl = 2 * (6 * D * (D + 1) + 3 * D * (D + 1) + D * (D + 1) + 4 * D * (D + 1) + D * (4 * D + 1) + 32);
  const double sgl = 7 * D * (D + 1) + D * (5 * D + 1) + 32 + 3 * D * (D + 1);
  CHECK(list.count() == dbl + sgl + 2 * D * (D + 1) + 3 * (D + 1));
  CHECK(list.count("dit.single_blocks.") == sgl);
}

TEST_CASE("a trunk of impossible widths is refused, naming them") {
  CHECK_THROWS_WITH_AS(Trunk(nn::DitWidths{30, 4, 120}, 1, 1, 3), doctest::Contains("heads 4"), Error);
  CHECK_THROWS_WITH_AS(Trunk(nn::DitWidths{32, 0, 128}, 1, 1, 3), doctest::Contains("heads 0"), Error);
  CHECK_THROWS_WITH_AS(Trunk(nn::DitWidths{32, 2, 128}, -1, 1, 3), doctest::Contains("blocks -1"), Error);
}
