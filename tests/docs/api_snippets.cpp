// The code snippets of docs/api.md, each as a function: this file compiling is the check that
// the page's calls exist with those arguments (issue #37: the decoding snippet called
// ModelConfigs::latent_h()). The functions are compiled, not run; keep them in step with the page.
#include <doctest/doctest.h>

#include <optional>
#include <string>
#include <vector>

#include "epona/cpu/context.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/world_session.hpp"
#include "epona/io/image.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/plan_choice.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "epona/nn/linear.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::api_snippets {

// "The window: History"
inline History window_snippet(const Dcae<Cpu, float>& dcae, std::int64_t F, std::int64_t L, std::int64_t H,
                              std::int64_t W) {
  cpu::Context ctx;
  std::vector<io::Image> frames;
  frames.push_back(io::read_image("frame.png", {.height = H, .width = W, .size = io::SizePolicy::Resize,
                                                .convert_to_rgb8 = true}));
  Tensor<float> z = dcae.encode(ctx, io::images_to_tensor(frames));
  Tensor<float> tokens = latent_to_tokens(ctx, z);
  io::PoseSequence all = io::load_poses("clip/poses.csv");
  io::PoseSequence p = all.slice(all.size() - F, F);
  History window{tokens.reshape({1, F, L, 32}), p.pose_tensor(), p.yaw_tensor()};
  return window;
}

// "An interactive session: WorldSession"
inline void session_snippet(WorldModel<Cpu, float>& wm, const Dcae<Cpu, float>& dcae, const std::vector<io::Image>& frames,
                            const io::PoseSequence& poses) {
  SampleOptions opt;
  opt.steps = 20;
  WorldSession<Cpu, float> session(wm, dcae, opt);
  session.reset(frames, poses);
  SessionStep s = session.step();
  SessionStep t = session.step(Motion{2.0f, 0.0f, 1.5f});
  io::write_png("next.png", t.frame);
  const History& w = session.window();
  cpu::Context ctx;
  History made = model::make_window(ctx, dcae.encode(ctx, io::images_to_tensor(frames)), poses);
  session.reset_latents(dcae.encode(ctx, io::images_to_tensor(frames)), poses);
  (void)s, (void)w, (void)made, (void)session.arena_capacity();
}

// "Planning, one step, a rollout"
inline void planning_snippet(WorldModel<Cpu, float>& wm, const History& window, const NextAction& action) {
  SampleOptions opt;
  opt.seed = 42;
  Tensor<float> plan = wm.plan(window, opt);
  StepResult next = wm.predict_next(window, std::nullopt, opt);
  StepResult ctrl = wm.predict_next(window, NextAction{action.rel_pose, action.rel_yaw}, opt);
  Tensor<float> fan = wm.plan_hypotheses(window, 8, opt);
  model::PlanFan pick = model::choose_plan(fan, model::PlanChoice::medoid);

  RolloutOptions ro;
  ro.frames = 54;
  ro.sample = opt;
  RolloutResult out = rollout(wm, window, ro, [](const RolloutFrame<Cpu>& f) { (void)f.result.latent, (void)f.window; });

  NoiseSource noise = NoiseSource::seeded(opt.seed);
  StepResult step = wm.run_step(window, nullptr, true, 10, noise, {});
  Tensor<float> waypoint0({1, 1, 3});
  History slid = window;
  model::slide_window(slid, step.latent, waypoint0);
  wm.context().set_threads(2);
  (void)plan, (void)next, (void)ctrl, (void)out, (void)pick;
}

// "Decoding"
inline void decoding_snippet(const Dcae<Cpu, float>& dcae, const io::ModelConfigs& cfg, const Tensor<float>& latents) {
  cpu::Context ctx;
  Tensor<float> z = tokens_to_latent(ctx, latents, cfg.world.latent_h(), cfg.world.latent_w());
  Tensor<float> images = dcae.decode(ctx, z, /*is_video=*/true);
  CHECK(images.size(0) % cfg.dcae.condition_frames == 0);
  io::write_png("frame.png", io::tensor_to_image(images, 0));
}

// "Loading"
inline void loading_snippet() {
  const io::ModelConfigs cfg = io::load_configs("configs.json");
  auto wm = WorldModel<Cpu, float>::load(io::load_weights("world.pkl"), cfg.world);
  auto wm2 = WorldModel<Cpu, bf16>::load_file("world.safetensors", cfg.world);
  auto dcae = Dcae<Cpu, float>::load(io::load_weights("dcae.safetensors"), cfg.dcae);
  (void)wm, (void)wm2, (void)dcae;
}

// "The parameter tree"
template <class B, class W>
struct GatedMlp : nn::Bindable<GatedMlp<B, W>> {
  nn::Linear<B, W> gate{64, 256, true}, out{256, 64, true};
  template <class V>
  void visit_params(const std::string& prefix, V& v) {
    gate.visit_params(prefix + "gate.", v);
    out.visit_params(prefix + "out.", v);
  }
};
inline io::TensorMap parameter_tree_snippet() {
  GatedMlp<Cpu, float> mlp;
  mlp.randomize(/*seed=*/1);                                        // or bind(map, "mlp.", report)
  const nn::ParamList list = mlp.parameters("mlp.");                // mlp.gate.weight [256, 64], ...
  const io::TensorMap stand_in = list.random_map(7, "stand-in");    // a checkpoint of its names
  return stand_in;
}

}  // namespace epona::api_snippets

TEST_CASE("docs/api.md: the snippets compile (see the functions above)") {
  // Taking their addresses keeps every snippet compiled.
  namespace s = epona::api_snippets;
  const bool taken = &s::window_snippet && &s::planning_snippet && &s::decoding_snippet && &s::loading_snippet &&
                     &s::session_snippet;
  CHECK(taken);
  CHECK(s::parameter_tree_snippet().size() == 4);  // this one needs no files: it runs
}

// stb is compiled in exactly one translation unit, after every other include.
#include "epona/io/stb_implementation.hpp"
