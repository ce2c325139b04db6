// example_custom_dit — a diffusion transformer of one's own, assembled from the kit's blocks
// (docs/api.md, "Building a model from the blocks"): a token embedding and a condition embedding
// (nn::Linear), a timestep embedding (nn::MlpEmbedder), and a trunk of 2 double-stream and 2
// single-stream FLUX blocks with its final layer (nn::DitTrunk), sampled from noise by the
// rectified-flow Euler solver. Random weights here; the same bind() takes a checkpoint's.
//
// usage: example_custom_dit [STEPS]   (default 10)
#include <cmath>
#include <cstdio>
#include <string>

#include "epona/core/arena.hpp"
#include "epona/cpu/context.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/nn/blocks/dit_trunk.hpp"
#include "epona/nn/embeddings.hpp"
#include "epona/nn/mlp.hpp"

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
int main(int argc, char** argv) {
  using B = Cpu;
  using Model = TinyDit<B, float>;
  try {
    std::int64_t steps = 10, Lc = 8, Lx = 24;
    if (argc > 1) {
      std::size_t used = 0;
      steps = std::stoll(argv[1], &used);
      EPONA_CHECK(used == std::string(argv[1]).size(), "STEPS must be a whole number, got '", argv[1], "'");
    }
    Model model;
    model.randomize(/*seed=*/7);
    std::printf("TinyDit: %.0f parameters in %zu tensors\n", model.parameters().count(),
                model.parameters().entries().size());

    cpu::Context ctx;
    Arena<B> arena(64 << 20);
    // The condition: Lc tokens of `channels` values, embedded once (step-invariant).
    Tensor<float> cond({Lc, Model::channels}), x({Lx, Model::channels}), v({Lx, Model::channels});
    nn::RandomValues noise(11);
    cond = noise.operator()<float>("cond", cond.shape());
    x = noise.operator()<float>("noise", x.shape());
    Tensor<float> cond_z({Lc, Model::hidden});
    model.cond_in(ctx, cond, cond_z);
    // RoPE over one axis: the condition at positions 0..Lc-1, the targets after them.
    Tensor<float> ids({Lc + Lx, 1});
    for (std::int64_t i = 0; i < Lc + Lx; ++i) ids.data()[i] = float(i);
    const nn::RopeTable<B> rope = nn::nd_rope_table(ids, {Model::hidden / Model::heads}, 10000.0);

    flow::FlowSolver<B, flow::EulerRule> solver(flow::get_schedule(steps, Lx));
    solver.sample(ctx, x, v, [&](std::int64_t, float t, const Tensor<float>& state, Tensor<float>& vel) {
      model.velocity(ctx, arena, state, cond_z, t, rope, vel);
    });

    double sum = 0, sq = 0;
    for (std::int64_t i = 0; i < x.numel(); ++i) sum += x.data()[i], sq += double(x.data()[i]) * x.data()[i];
    const double mean = sum / double(x.numel()), rms = std::sqrt(sq / double(x.numel()));
    EPONA_CHECK(std::isfinite(mean) && std::isfinite(rms), "the sample is not finite");
    std::printf("sampled (%lld, %lld) in %lld Euler steps: mean %.4f, rms %.4f\n", (long long)Lx,
                (long long)Model::channels, (long long)steps, mean, rms);
  } catch (const std::logic_error&) {  // std::stoll's invalid_argument / out_of_range
    std::fprintf(stderr, "example_custom_dit: STEPS must be a whole number, got '%s'\n", argv[1]);
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "example_custom_dit: %s\n", e.what());
    return 1;
  }
}
