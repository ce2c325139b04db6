// Tensor parallelism (core/tensor_parallel.hpp, nn/linear_shards.hpp, docs/parallel.md): a DiT split
// over 2 and 4 shards, each shard a thread with its own context and its weights cut from the
// whole model's map (cpu/thread_shard_sum.hpp), gives the whole DiT's velocity and samples, and
// every shard gives the same bits. Both test DiTs (tests/model/dit_cases.hpp), one item and a
// batch of two (the world model with its VisDiT split: the golden rollout, model/world_parity.cpp).
// The cuts themselves are checked against hand-made weights, and every misuse is refused with a
// message.
// Bound: float32 within 1e-6 relative (a shard sums its part of each product's terms, and the
// group adds the parts: another order of the same additions); the worst difference is printed.
#include <doctest/doctest.h>

#include <atomic>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include "../metrics.hpp"
#include "dit_cases.hpp"
#include "epona/cpu/thread_shard_sum.hpp"
#include "epona/nn/linear_shards.hpp"

using namespace epona;
using namespace epona::test::dit;
using epona::test::rel_max;

namespace {

void bind(Dit& dit, const io::TensorMap& map) {
  io::BindReport report(map);
  dit.bind(map, "", report);
  report.finish(true, [](const std::string&) { return false; });
}

bool same_bits(const Tensor<float>& a, const Tensor<float>& b) {
  return a.shape() == b.shape() && std::memcmp(a.data(), b.data(), a.nbytes()) == 0;
}

// The velocity and a 4-step Heun sample of `in` from every shard of a `shards`-way split of the
// DiT whose whole weights are `weights`.
struct ShardResults {
  std::vector<Tensor<float>> velocity, sample;
};
ShardResults run_shards(const Case& k, const io::TensorMap& weights, std::int64_t shards, const Inputs& in,
                        const Tensor<float>& t) {
  cpu::ThreadShardGroup group(shards);
  ShardResults out{std::vector<Tensor<float>>(shards), std::vector<Tensor<float>>(shards)};
  group.run([&](std::int64_t r) {
    model::FluxDitConfig config = k.config;
    config.shard = {r, shards};
    Dit part(config);
    bind(part, part.shard_weights(weights, ""));
    const auto sum = group.shard(r);
    part.set_shard_sum(&sum);
    cpu::Context c(1);
    out.velocity[r] = velocity(part, in, t, c);
    out.sample[r] = sample(part, in, 4, flow::SolverKind::heun, c);
  });
  return out;
}

// A hand-made map: `name` (rows, cols) with entry (r, c) = 100 r + c, and its bias b[r] = r + 1.
io::TensorMap linear_map(const std::string& prefix, std::int64_t rows, std::int64_t cols) {
  auto w = std::make_shared<Tensor<float>>(Shape{rows, cols});
  auto b = std::make_shared<Tensor<float>>(Shape{rows});
  for (std::int64_t r = 0; r < rows; ++r) {
    b->data()[r] = float(r + 1);
    for (std::int64_t c = 0; c < cols; ++c) w->at(r, c) = float(100 * r + c);
  }
  io::TensorMap map("hand-made");
  const auto raw = [](const Tensor<float>& t) {
    return io::RawTensor{DType::F32, t.shape(),
                         std::span<const std::byte>(reinterpret_cast<const std::byte*>(t.data()), t.nbytes())};
  };
  map.add(prefix + "weight", raw(*w));
  map.add(prefix + "bias", raw(*b));
  map.keep_alive(w);
  map.keep_alive(b);
  return map;
}
std::vector<float> values(const io::TensorMap& map, const std::string& name) {
  const Tensor<float> t = io::to_tensor<float>(map.at(name));
  return std::vector<float>(t.data(), t.data() + t.numel());
}

}  // namespace

TEST_CASE("a DiT split over 2 and 4 shards gives the whole DiT's velocity and samples on every shard") {
  for (const Case& k : {vis_like(), traj_like()}) {
    Dit whole(k.config);
    const io::TensorMap weights = whole.parameters().random_map(7, "random DiT", nn::WeightInit::torch_linear);
    bind(whole, weights);
    for (const std::int64_t items : {1, 2}) {
      const Inputs in = inputs(k, items);
      Tensor<float> t({items});
      for (std::int64_t b = 0; b < items; ++b) t.data()[b] = 0.3f + 0.4f * float(b);
      const auto v = velocity(whole, in, t);
      const auto x = sample(whole, in, 4, flow::SolverKind::heun);
      for (const std::int64_t shards : {2, 4}) {
        CAPTURE(std::string(k.name));
        CAPTURE(items);
        CAPTURE(shards);
        const ShardResults parts = run_shards(k, weights, shards, in, t);
        double worst = 0;
        for (std::int64_t r = 0; r < shards; ++r) {
          worst = std::max({worst, rel_max(parts.velocity[r], v), rel_max(parts.sample[r], x)});
          CHECK(same_bits(parts.velocity[r], parts.velocity[0]));
          CHECK(same_bits(parts.sample[r], parts.sample[0]));
        }
        MESSAGE(std::string(k.name), ", ", items, " item(s), ", shards,
                " shards: worst rel against the whole DiT (velocity, Heun x 4) ", worst);
        CHECK(worst <= 1e-6);
        CHECK(rel_max(parts.sample[0], in.x) > 1e-2);  // the sample moved: the comparison is not of inputs
      }
    }
  }
}

TEST_CASE("a shard's weights are its heads' rows and columns, the summed layers' bias on shard 0") {
  // Outputs in three segments (q, k, v of 2 heads of width 1): shard 1 of 2 keeps rows 1, 3, 5.
  const io::TensorMap qkv = linear_map("qkv.", 6, 2);
  const io::TensorMap cut = nn::shard_weights(qkv, {{"qkv.", nn::LinearSplit::outputs, {2, 2, 2}}}, {1, 2});
  CHECK(cut.at("qkv.weight").shape == Shape{3, 2});
  CHECK(values(cut, "qkv.weight") == std::vector<float>{100, 101, 300, 301, 500, 501});
  CHECK(values(cut, "qkv.bias") == std::vector<float>{2, 4, 6});
  // Inputs in two segments (attention 4, MLP 2): shard 1 of 2 keeps columns 2, 3 and 5; the bias
  // is shard 0's alone.
  const io::TensorMap out = linear_map("out.", 2, 6);
  const auto split = std::vector<nn::LinearSplit>{{"out.", nn::LinearSplit::inputs, {4, 2}}};
  const io::TensorMap second = nn::shard_weights(out, split, {1, 2});
  CHECK(values(second, "out.weight") == std::vector<float>{2, 3, 5, 102, 103, 105});
  CHECK(values(second, "out.bias") == std::vector<float>{0, 0});
  const io::TensorMap first = nn::shard_weights(out, split, {0, 2});
  CHECK(values(first, "out.weight") == std::vector<float>{0, 1, 4, 100, 101, 104});
  CHECK(values(first, "out.bias") == std::vector<float>{1, 2});
  // Tensors no split names pass through unchanged.
  CHECK(values(nn::shard_weights(out, {}, {1, 2}), "out.bias") == std::vector<float>{1, 2});
}

TEST_CASE("tensor-parallel misuse is refused with a message") {
  const Case k = vis_like();  // 4 heads, MLP 256
  model::FluxDitConfig c = k.config;
  c.shard = {0, 3};
  CHECK_THROWS_WITH_AS(Dit{c}, doctest::Contains("3 shards must divide the 4 heads"), Error);
  c.shard = {2, 2};
  CHECK_THROWS_WITH_AS(Dit{c}, doctest::Contains("shard 2 of 2"), Error);

  // A shard without its group's sum, or with a group of another size.
  c.shard = {0, 2};
  Dit part(c);
  Dit whole(k.config);
  const io::TensorMap weights = whole.parameters().random_map(7, "random DiT", nn::WeightInit::torch_linear);
  bind(part, part.shard_weights(weights, ""));
  const Inputs in = inputs(k, 1);
  Tensor<float> t({1});
  CHECK_THROWS_WITH_AS(velocity(part, in, t), doctest::Contains("needs the group's sum"), Error);
  cpu::ThreadShardGroup four(4);
  const auto sum = four.shard(0);
  CHECK_THROWS_WITH_AS(part.set_shard_sum(&sum), doctest::Contains("a group of 4 shards for a trunk sharded 2 ways"),
                       Error);

  // Weights that do not fit the split.
  const auto split = std::vector<nn::LinearSplit>{{"qkv.", nn::LinearSplit::outputs, {3, 3}}};
  CHECK_THROWS_WITH_AS(nn::shard_weights(linear_map("qkv.", 6, 2), split, {0, 2}),
                       doctest::Contains("a segment of 3 entries does not split over 2 shards"), Error);
  CHECK_THROWS_WITH_AS(nn::shard_weights(linear_map("qkv.", 5, 2), split, {0, 2}),
                       doctest::Contains("its dimension has 5 entries, the model's widths give 6"), Error);
  CHECK_THROWS_WITH_AS(nn::shard_weights(linear_map("qkv.", 6, 2), split, {-1, 2}), doctest::Contains("shard -1 of 2"),
                       Error);
}

TEST_CASE("a shard that fails stops its group: the others do not wait for it") {
  cpu::ThreadShardGroup group(3);
  std::atomic<int> stopped{0};
  const auto work = [&](std::int64_t r) {
    if (r == 1) throw Error("shard 1 could not read its weights");
    std::vector<float> partial(8, 1.f);
    cpu::Context c(1);
    try {
      group.shard(r).sum(c, partial.data(), 8);
    } catch (const Error&) {
      ++stopped;
      throw;
    }
  };
  CHECK_THROWS_WITH_AS(group.run(work), "shard 1 could not read its weights", Error);
  CHECK(stopped == 2);

  cpu::ThreadShardGroup sums(2);
  std::vector<std::vector<float>> parts{{1, 2, 3}, {10, 20, 30}};
  sums.run([&](std::int64_t r) {
    cpu::Context c(1);
    sums.shard(r).sum(c, parts[r].data(), 3);
  });
  CHECK(parts[0] == std::vector<float>{11, 22, 33});
  CHECK(parts[1] == parts[0]);
  cpu::ThreadShardGroup uneven(2);
  CHECK_THROWS_WITH_AS(uneven.run([&](std::int64_t r) {
                         cpu::Context c(1);
                         uneven.shard(r).sum(c, parts[r].data(), r + 1);
                       }),
                       doctest::Contains("buffers of different sizes"), Error);
}
