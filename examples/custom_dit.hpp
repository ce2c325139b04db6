// examples/custom_dit.hpp — the DiT of examples/custom_dit.cpp (CPU) and custom_dit_cuda.cu (the
// same on a GPU, against the CPU): a diffusion transformer of one's own, assembled from the
// kit's blocks (docs/api.md, "Building a model from the blocks").
#pragma once

#include <stdexcept>
#include <string>

#include "epona/core/arena.hpp"
#include "epona/core/backend_traits.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/nn/blocks/dit_trunk.hpp"
#include "epona/nn/embeddings.hpp"
#include "epona/nn/mlp.hpp"

namespace example {
using namespace epona;

// ---- the model: about 40 lines ----
template <class B, class W>
struct TinyDit : nn::Bindable<TinyDit<B, W>> {
  using A = Activation<B, W>;
  static constexpr std::int64_t channels = 16, hidden = 64, heads = 4, time_dim = 32;
  nn::Linear<B, W> x_in{channels, hidden, true}, cond_in{channels, hidden, true};
  nn::MlpEmbedder<B, W> time_in{time_dim, hidden};
  nn::DitTrunk<B, W> trunk{nn::DitWidths{hidden, heads, 4 * hidden}, 2, 2, channels};

  // The parameter tree: binding, random values and parameter counts all walk it.
  template <class V>
  void visit_params(const std::string& p, V& v) {
    x_in.visit_params(p + "x_in.", v);
    cond_in.visit_params(p + "cond_in.", v);
    time_in.visit_params(p + "time_in.", v);
    trunk.visit_params(p, v);  // double_blocks.i., single_blocks.j., final_layer.
  }

  // One velocity v = DiT(x, t | cond) of one sequence: x (Lx, channels) target tokens, cond_z
  // (Lc, hidden) the embedded condition, `rope` the table of the Lc + Lx rows.
  void velocity(BackendContext<B>& ctx, Arena<B>& arena, const Tensor<A, B>& x, const Tensor<A, B>& cond_z, float t,
                const nn::RopeTable<B>& rope, Tensor<A, B>& v) const {
    ArenaScope<B> scope(arena);
    const nn::JointRows rows{cond_z.size(0), x.size(0)};
    // The adaLN table row of timestep t: every block's (shift, scale, gate) from SiLU(time_in(temb(t))).
    Tensor<float, Cpu> temb({1, time_dim});
    nn::timestep_embedding(&t, 1, time_dim, 10000.0, 1000.0f, temb.data());
    auto emb = arena.template take<A>({1, time_dim}), h = arena.template take<A>({1, hidden}),
         vec = arena.template take<A>({1, hidden}), table = arena.template take<A>({1, trunk.modulation_width()});
    upload_as(ctx, temb, emb);
    time_in(ctx, emb, h, vec);
    silu_to(ctx, vec.data(), h.data(), hidden);
    trunk.modulations(ctx, h.data(), 1, table.data(), trunk.modulation_width());
    // The target rows of z; the trunk reads the condition rows from cond_z in place.
    auto s = trunk.plan_scratch(arena, rows);
    auto target = s.z.slice(rows.cond, rows.total());
    x_in(ctx, x, target);
    trunk(ctx, s, rows, rope, table.data(), v, {cond_z.data(), {}});
  }
};

// ---- using it: random weights, a condition, 1-D RoPE positions, and the Euler sampler ----
// Samples Lx = 24 target tokens from seeded noise under a seeded condition of Lc = 8 tokens, on
// backend B; returns the sample on the host.
template <class B>
Tensor<float, Cpu> sample_tiny_dit(BackendContext<B>& ctx, std::int64_t steps, std::uint64_t seed) {
  using Model = TinyDit<B, float>;
  constexpr std::int64_t Lc = 8, Lx = 24;
  Model model;
  model.randomize(/*seed=*/7);
  Arena<B> arena(16 << 20);
  nn::RandomValues values(seed);
  const auto cond = BackendTraits<B>::upload(values.operator()<float>("cond", {Lc, Model::channels}));
  auto x = BackendTraits<B>::upload(values.operator()<float>("noise", {Lx, Model::channels}));
  Tensor<float, B> v({Lx, Model::channels}), cond_z({Lc, Model::hidden});
  model.cond_in(ctx, cond, cond_z);  // the condition, embedded once (step-invariant)
  // RoPE over one axis: the condition at positions 0..Lc-1, the targets after them.
  Tensor<float, Cpu> ids({Lc + Lx, 1});
  for (std::int64_t i = 0; i < Lc + Lx; ++i) ids.data()[i] = float(i);
  const auto rope = nn::upload<B>(nn::nd_rope_table(ids, std::vector<std::int64_t>{Model::hidden / Model::heads}, 10000.0));

  flow::FlowSolver<B, flow::EulerRule> solver(flow::get_schedule(steps, Lx));
  solver.sample(ctx, x, v, [&](std::int64_t, float t, const Tensor<float, B>& state, Tensor<float, B>& vel) {
    model.velocity(ctx, arena, state, cond_z, t, rope, vel);
  });
  return host_tensor<B>(ctx, x);
}

// STEPS from the command line, whole or refused.
inline std::int64_t steps_argument(int argc, char** argv) {
  if (argc < 2) return 10;
  std::size_t used = 0;
  std::int64_t steps = -1;
  try {
    steps = std::stoll(argv[1], &used);
  } catch (const std::logic_error&) {  // invalid_argument, out_of_range
  }
  EPONA_CHECK(used > 0 && used == std::string(argv[1]).size(), "STEPS must be a whole number, got '", argv[1], "'");
  return steps;
}

}  // namespace example
