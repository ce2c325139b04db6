// WorldSession on the conformance model (tests/data/golden) and its 3-frame demo clip: its
// self-predicted steps equal model::rollout's, its steps with given actions equal the CLI
// rollout's (run_step with one noise source, then slide_window), the frame is the latent decoded
// alone, repeated steps keep the window's buffers and the model's arena, and bad input is
// refused with an epona::Error naming the problem.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/world_session.hpp"
#include "epona/io/image.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/model/rollout.hpp"
#include "../error_text.hpp"

using namespace epona;
using epona::test::contains;
using epona::test::error_of;

namespace {

const std::string kGolden = std::string(EPONA_TEST_DATA_DIR) + "/golden";
const std::string kClip = std::string(EPONA_TEST_DATA_DIR) + "/demo";

struct Loaded {
  io::ModelConfigs cfg = io::load_configs(kGolden + "/configs.json");
  WorldModel<Cpu, float> world = WorldModel<Cpu, float>::load_file(kGolden + "/weights_world.safetensors", cfg.world);
  Dcae<Cpu, float> dcae = Dcae<Cpu, float>::load(io::load_weights(kGolden + "/weights_dcae.safetensors"), cfg.dcae);
  std::vector<io::Image> frames;
  io::PoseSequence poses = io::load_poses(kClip + "/poses.csv");
  Loaded() {
    for (int i = 0; i < 3; ++i) frames.push_back(io::read_image(kClip + "/frame_0" + std::to_string(i) + ".png"));
  }
};

Loaded& loaded() {
  static Loaded l;
  return l;
}

SampleOptions few_steps(std::uint64_t seed) {
  SampleOptions o;
  o.steps = 3;
  o.seed = seed;
  return o;
}

// The window a session starts from, made as the CLI makes it.
History clip_window(Loaded& l) {
  return model::make_window(l.world.context(), l.dcae.encode(l.world.context(), io::images_to_tensor(l.frames)), l.poses);
}

bool same(const Tensor<float, Cpu>& a, const Tensor<float, Cpu>& b) {
  if (a.shape() != b.shape()) return false;
  for (std::int64_t i = 0; i < a.numel(); ++i)
    if (a.data()[i] != b.data()[i]) return false;
  return true;
}

}  // namespace

TEST_CASE("session steps without actions equal model::rollout, step by step") {
  auto& l = loaded();
  RolloutOptions ro;
  ro.frames = 3;
  ro.sample = few_steps(7);
  const RolloutResult ref = rollout(l.world, clip_window(l), ro);

  WorldSession<> s(l.world, l.dcae, few_steps(7));
  s.reset(l.frames, l.poses);
  for (std::int64_t i = 0; i < ro.frames; ++i) {
    const SessionStep step = s.step();
    CHECK(same(step.trajectory, ref.trajectories[i][0]));
    CHECK(same(step.latent, ref.latents[i][0]));
    CHECK(step.motion.x == ref.trajectories.at(i, 0, 0, 0));
    CHECK(step.motion.yaw == ref.trajectories.at(i, 0, 0, 2));
    CHECK(step.frame.height == l.cfg.world.image_h);
    CHECK(step.frame.width == l.cfg.world.image_w);
  }
  CHECK(same(s.window().latents, ref.window.latents));
  CHECK(same(s.window().rel_pose, ref.window.rel_pose));
  CHECK(same(s.window().rel_yaw, ref.window.rel_yaw));
  CHECK(s.steps_taken() == 3);
}

TEST_CASE("session steps with actions equal the CLI's rollout: run_step with one noise source, then a slide") {
  auto& l = loaded();
  const std::vector<Motion> actions{{1.5f, 0.1f, 2.0f}, {1.0f, -0.2f, -1.0f}};
  History window = clip_window(l);
  NoiseSource noise = NoiseSource::seeded(11);
  WorldSession<> s(l.world, l.dcae, few_steps(11));
  s.reset(l.frames, l.poses);
  for (const Motion& m : actions) {
    NextAction act{Tensor<float, Cpu>({1, 1, 2}), Tensor<float, Cpu>({1, 1, 1})};
    act.rel_pose.data()[0] = m.x, act.rel_pose.data()[1] = m.y, act.rel_yaw.data()[0] = m.yaw;
    const StepResult r = l.world.run_step(window, &act, true, l.world.samplers_of(few_steps(11)), noise, {});
    Tensor<float, Cpu> used({1, 1, 3});
    used.data()[0] = m.x, used.data()[1] = m.y, used.data()[2] = m.yaw;
    model::slide_window(window, r.latent, used);

    const SessionStep step = s.step(m);
    CHECK(step.trajectory.empty());
    CHECK(same(step.latent, r.latent[0]));
    CHECK(step.motion.x == m.x);
    // The frame is the new latent decoded alone.
    const auto decoded = l.dcae.decode(l.world.context(),
                                       tokens_to_latent(l.world.context(), r.latent, l.cfg.world.latent_h(),
                                                        l.cfg.world.latent_w()), false);
    CHECK(step.frame.rgb == io::tensor_to_image(decoded, 0).rgb);
  }
  CHECK(same(s.window().latents, window.latents));
  CHECK(same(s.window().rel_pose, window.rel_pose));
}

TEST_CASE("repeated steps reuse the window's buffers and the model's arena") {
  auto& l = loaded();
  WorldSession<> s(l.world, l.dcae, few_steps(3));
  s.reset(l.frames, l.poses);
  s.step();
  const std::size_t arena = s.arena_capacity();
  const float* latents = s.window().latents.data();
  const float* pose = s.window().rel_pose.data();
  CHECK(arena > 0);
  for (int i = 0; i < 3; ++i) {
    s.step(i % 2 ? std::optional<Motion>() : Motion{1.0f, 0.0f, 0.0f});
    CHECK(s.arena_capacity() == arena);
    CHECK(s.window().latents.data() == latents);
    CHECK(s.window().rel_pose.data() == pose);
  }
  // The last slid-in motion is the last step's action or waypoint 0, and reset() starts over.
  s.reset(l.frames, l.poses);
  CHECK(s.steps_taken() == 0);
  CHECK(s.window().rel_pose.at(0, 0, 0) == 0.0f);  // make_window: the first frame gets no motion
}

TEST_CASE("a session over bf16 weights steps like the float32 one, within bf16's rounding") {
  auto& l = loaded();
  auto world = WorldModel<Cpu, bf16>::load_file(kGolden + "/weights_world.safetensors", l.cfg.world);
  const auto dcae = Dcae<Cpu, bf16>::load(io::load_weights(kGolden + "/weights_dcae.safetensors"), l.cfg.dcae);
  WorldSession<Cpu, bf16> s(world, dcae, few_steps(5));
  WorldSession<> f(l.world, l.dcae, few_steps(5));
  s.reset(l.frames, l.poses);
  f.reset(l.frames, l.poses);
  const SessionStep a = s.step(), b = f.step();
  REQUIRE(a.trajectory.shape() == b.trajectory.shape());
  double worst = 0;
  for (std::int64_t i = 0; i < a.trajectory.numel(); ++i)
    worst = std::max(worst, double(std::abs(a.trajectory.data()[i] - b.trajectory.data()[i])));
  MESSAGE("bf16 vs float32 plan, largest difference: ", worst);
  CHECK(worst < 0.5);  // metres/degrees; the golden weights are random, so only a loose bound
  CHECK(a.frame.height == b.frame.height);
}

TEST_CASE("a session refuses bad input, naming the problem") {
  auto& l = loaded();
  WorldSession<> s(l.world, l.dcae, few_steps(0));
  CHECK(contains(error_of([&] { s.step(); }), "call reset()"));

  std::vector<io::Image> two(l.frames.begin(), l.frames.begin() + 2);
  CHECK(contains(error_of([&] { s.reset(two, l.poses); }), "2 frame(s) given; the model needs 3"));

  std::vector<io::Image> small = l.frames;
  small[1] = io::Image(32, 64);
  CHECK(contains(error_of([&] { s.reset(small, l.poses); }), "frame 1 is 32x64; the model takes 64x128"));

  io::PoseSequence nan_pose = l.poses;
  nan_pose.y[2] = std::numeric_limits<float>::quiet_NaN();
  CHECK(contains(error_of([&] { s.reset(l.frames, nan_pose); }), "pose 2"));
  CHECK(contains(error_of([&] { s.reset(l.frames, l.poses.slice(0, 2)); }), "2 pose(s) given"));

  s.reset(l.frames, l.poses);
  CHECK(contains(error_of([&] { s.step(Motion{1.0f, std::numeric_limits<float>::infinity(), 0.0f}); }),
                 "the action"));
  CHECK(s.steps_taken() == 0);
}

// stb is compiled in exactly one translation unit, after every other include.
#include "epona/io/stb_implementation.hpp"
