// The small DiTs and inputs that the DiT model tests share (tests/model/dit_batch.cpp,
// tests/model/dit_shards.cpp): a VisDiT-like DiT (an action vector, streams paired at batch 1)
// and a TrajDiT-like one (no action, the pipelined condition front), items that differ in
// condition, action, ids and noise, and forward()/sample() on the CPU.
#pragma once

#include <algorithm>
#include <random>
#include <string>

#include "../cpu_context.hpp"
#include "epona/core/arena.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/model/flux_dit.hpp"

namespace epona::test::dit {

using Dit = model::FluxDiT<Cpu, float>;

inline cpu::Context& ctx() { return cpu_context(); }

inline Tensor<float> random(const Shape& shape, std::uint32_t seed, float scale = 1.f) {
  std::mt19937 gen(seed);
  std::normal_distribution<float> dist(0.f, scale);
  Tensor<float> t(shape);
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = dist(gen);
  return t;
}

// Item b of a batched tensor as a batch of one.
inline Tensor<float> item(const Tensor<float>& t, std::int64_t b) {
  Shape s = t.shape();
  s[0] = 1;
  return t.slice(b, b + 1).clone().reshape(s);
}

struct Case {
  const char* name;
  model::FluxDitConfig config;
  nn::JointRows rows;
};

inline Case vis_like() {
  model::FluxDitConfig c;
  c.in_channels = c.out_channels = 8;
  c.context_in_dim = 24;
  c.hidden_size = 64;
  c.num_heads = 4;
  c.depth = 2;
  c.depth_single_blocks = 2;
  c.vec_in_dim = 12;
  c.axes_dim = {4, 6, 6};
  return {"VisDiT-like (paired streams, an action)", c, {10, 9}};
}
inline Case traj_like() {
  Case c = vis_like();
  c.name = "TrajDiT-like (unpaired streams, pipelined front)";
  c.config.vec_in_dim = 0;
  c.config.input_name = "traj_in";
  c.config.in_channels = c.config.out_channels = 3;
  c.rows = {10, 3};
  return c;
}

// The inputs of `items` scenes: condition, action, ids (each item its own), noise.
struct Inputs {
  Tensor<float> cond, y, cond_ids, target_ids, x;
};
inline Inputs inputs(const Case& k, std::int64_t items) {
  const auto& c = k.config;
  Inputs in{random({items, k.rows.cond, c.context_in_dim}, 1), random({items, std::max<std::int64_t>(c.vec_in_dim, 1)}, 2),
            Tensor<float>({items, k.rows.cond, 3}), Tensor<float>({items, k.rows.target, 3}),
            random({items, k.rows.target, c.in_channels}, 3)};
  if (c.vec_in_dim == 0) in.y = Tensor<float>();
  // Ids: condition rows (b, 0, 0), target rows (r, r + b, r + 2b); a new tensor is not zeroed.
  std::fill_n(in.cond_ids.data(), in.cond_ids.numel(), 0.f);
  for (std::int64_t b = 0; b < items; ++b) {
    for (std::int64_t r = 0; r < k.rows.cond; ++r) in.cond_ids.at(b, r, 0) = float(b);
    for (std::int64_t r = 0; r < k.rows.target; ++r)
      for (std::int64_t a = 0; a < 3; ++a) in.target_ids.at(b, r, a) = float(r + a * b);
  }
  return in;
}
inline Inputs item(const Inputs& in, std::int64_t b) {
  return {item(in.cond, b), in.y.empty() ? Tensor<float>() : item(in.y, b), item(in.cond_ids, b),
          item(in.target_ids, b), item(in.x, b)};
}

// (Templates: a file that only uses the cases, such as a GPU test, compiles no CPU model.)
template <class Model>
Tensor<float> velocity(const Model& dit, const Inputs& in, const Tensor<float>& t, cpu::Context& c = ctx()) {
  const std::int64_t batch = in.x.size(0);
  const nn::JointRows rows{in.cond.size(1), in.x.size(1)};
  Arena<Cpu> arena(dit.forward_bytes(batch, rows));
  Tensor<float> v(in.x.shape());
  dit.forward(c, arena, in.x, in.target_ids, in.cond, in.cond_ids, t, in.y, v);
  return v;
}

template <class Model>
Tensor<float> sample(const Model& dit, const Inputs& in, std::int64_t steps, flow::SolverKind kind,
                            cpu::Context& c = ctx()) {
  const std::int64_t batch = in.x.size(0);
  const nn::JointRows rows{in.cond.size(1), in.x.size(1)};
  Arena<Cpu> arena(dit.conditioning_bytes(batch, rows) + dit.sample_bytes(batch, rows, steps, kind));
  auto state = in.x.clone();
  const auto conditioning = dit.prepare(c, arena, in.cond, in.cond_ids, in.target_ids, in.y);
  dit.sample(c, arena, conditioning, flow::get_schedule(steps, rows.target), state, kind);
  return state;
}

}  // namespace epona::test::dit
