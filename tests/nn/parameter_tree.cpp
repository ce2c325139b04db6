// nn/parameter.hpp, the parameter tree: the visitors over a module's visit_params — the listing
// (names, shapes, counts), binding from a weight map (stacked parts in one allocation, every
// problem reported), random values (their rule, their determinism, stacked too) — and that a
// random map bound back gives its own values.
#include <doctest/doctest.h>

#include <cmath>
#include <string>

#include "epona/nn/linear.hpp"
#include "epona/nn/mlp.hpp"
#include "epona/nn/parameter.hpp"

using namespace epona;

namespace {

// Two linear layers stacked (as a DiT double block's two streams) and one alone.
struct PairAndOne : nn::Bindable<PairAndOne> {
  nn::Linear<Cpu, float> a{6, 4, true}, b{6, 4, true}, c{4, 3, false};
  template <class V>
  void visit_params(const std::string& p, V& v) {
    nn::Linear<Cpu, float>::visit_pair(v, a, p + "a.", b, p + "b.");
    c.visit_params(p + "c.", v);
  }
};

bool same_values(const Tensor<float>& t, const Tensor<float>& u) {
  if (t.numel() != u.numel()) return false;
  for (std::int64_t i = 0; i < t.numel(); ++i)
    if (t.data()[i] != u.data()[i]) return false;
  return true;
}

}  // namespace

TEST_CASE("ParamList names every parameter in visiting order, with its shape, and counts them") {
  const nn::ParamList list = PairAndOne().parameters("m.");
  std::vector<std::string> names;
  for (const auto& e : list.entries()) names.push_back(e.name);
  CHECK(names == std::vector<std::string>{"m.a.weight", "m.b.weight", "m.a.bias", "m.b.bias", "m.c.weight"});
  CHECK(list.entries()[0].shape == Shape{4, 6});
  CHECK(list.entries()[4].shape == Shape{3, 4});
  CHECK(list.count() == 2 * 24 + 2 * 4 + 12);
  CHECK(list.count("m.a.") == 28);
  CHECK(list.count("m.z") == 0);
}

TEST_CASE("a random map bound back gives its values; stacked parts share one allocation") {
  const io::TensorMap map = PairAndOne().parameters().random_map(5, "random");
  PairAndOne m;
  io::BindReport report(map);
  m.bind(map, "", report);
  CHECK_NOTHROW(report.finish(true));
  CHECK(same_values(m.a.weight, io::to_tensor<float>(map.at("a.weight"))));
  CHECK(same_values(m.b.bias, io::to_tensor<float>(map.at("b.bias"))));
  CHECK(same_values(m.c.weight, io::to_tensor<float>(map.at("c.weight"))));
  CHECK(m.b.weight.data() - m.a.weight.data() == 24);  // one matrix apart, a first
  CHECK(m.b.bias.data() - m.a.bias.data() == 4);
}

TEST_CASE("binding reports every missing or mis-shaped part, and binds none of a broken stack") {
  const io::TensorMap full = PairAndOne().parameters().random_map(5, "random");
  io::TensorMap broken("broken");
  for (const auto& name : full.names())
    if (name != "b.weight" && name != "c.weight") broken.add(name, full.at(name));
  broken.add("c.weight", full.at("a.bias"));  // (4) where (3, 4) belongs
  PairAndOne m;
  io::BindReport report(broken);
  m.bind(broken, "", report);
  CHECK_FALSE(report.ok());
  CHECK_THROWS_WITH_AS(report.finish(true), doctest::Contains("missing 'b.weight' (expected shape (4, 6))"), Error);
  CHECK_THROWS_WITH_AS(report.finish(true), doctest::Contains("'c.weight' has shape (4,), expected (3, 4)"), Error);
  CHECK(m.a.weight.empty());  // the pair's weights are one allocation: none without both
  CHECK_FALSE(m.a.bias.empty());
}

TEST_CASE("random values: seeded, stacked in one allocation, at the scale of their kind") {
  PairAndOne x, y, z;
  x.randomize(9);
  y.randomize(9);
  z.randomize(10);
  CHECK(same_values(x.a.weight, y.a.weight));
  CHECK_FALSE(same_values(x.a.weight, z.a.weight));
  CHECK(x.b.weight.data() - x.a.weight.data() == 24);
  // Matrices: uniform with variance 1/fan_in, so |w| < sqrt(3/fan_in); vectors named bias near 0.
  for (std::int64_t i = 0; i < x.a.weight.numel(); ++i) CHECK(std::abs(x.a.weight.data()[i]) < std::sqrt(3.0f / 6));
  for (std::int64_t i = 0; i < x.a.bias.numel(); ++i) CHECK(std::abs(x.a.bias.data()[i]) <= 0.1f);
  // Vectors named weight or scale (norm scales) near 1.
  nn::RandomValues values(1);
  const Tensor<float> scale = values.operator()<float>("norm.scale", {64});
  for (std::int64_t i = 0; i < scale.numel(); ++i) CHECK(std::abs(scale.data()[i] - 1.0f) <= 0.2f);
}
