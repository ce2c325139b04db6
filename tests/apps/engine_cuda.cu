// The epona program's CUDA engine (apps/epona/engine.hpp, ModelEngine<Cuda, W>, what
// `--backend cuda` runs) against its CPU engine on the golden model (EPONA_GOLDEN_DIR): DC-AE
// encode and decode (frame and clip), plan, and two rollout steps sharing one noise source.
// Tolerances as the GPU parity tests (golden README): float32 rel_max <= 1e-4 per stage, 1e-3
// after a rollout step; bf16 runs and gives finite values of the right shapes. Skips without a GPU.
#include <doctest/doctest.h>

#include <cmath>
#include <cstdlib>
#include <string>

#include "../metrics.hpp"
#include "../../apps/epona/engine.hpp"
#include "../../apps/epona/frames.hpp"
#include "../../apps/epona/rollout_common.hpp"
#include "../cuda/cuda_test_util.cuh"
#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"
#include "epona/cuda/runtime/scratch.hpp"
#include "epona/domain/world_session.hpp"
#include "epona/model/rollout.hpp"
#include "../golden_dir.hpp"

using namespace epona;
using epona::test::golden_dir;
using epona::test::rel_max;

namespace {

app::ModelFiles golden_files() {
  app::ModelFiles f;
  f.world = golden_dir() + "/weights_world.safetensors";
  f.dcae = golden_dir() + "/weights_dcae.safetensors";
  f.configs = io::load_configs(golden_dir() + "/configs.json");
  f.config_source = golden_dir() + "/configs.json";
  return f;
}

bool all_finite(const Tensor<float>& t) {
  for (std::int64_t i = 0; i < t.numel(); ++i)
    if (!std::isfinite(t.data()[i])) return false;
  return true;
}

std::unique_ptr<app::Engine> loaded(const std::string& backend, bool bf16_weights, const app::ModelFiles& f) {
  std::ostringstream sink;
  const app::Console quiet{sink, sink, true, false};
  app::ComputeOptions c;
  c.backend = backend;
  c.bf16_weights = bf16_weights;
  // the program's own engines: this test links its build of the commands (epona_commands), whose
  // make_cuda_engine (apps/epona/cuda_engine.cu) builds the CUDA one
  std::unique_ptr<app::Engine> e = app::make_engine(c);
  e->load_dcae(f, quiet);
  e->load_world(f, quiet);
  return e;
}

// The golden model's window from the demo frames (resized) and 2 m-per-frame motions.
History window_of(app::Engine& e, const WorldModelConfig& w) {
  std::vector<io::Image> frames;
  io::PoseSequence poses;
  for (std::int64_t i = 0; i < w.condition_frames; ++i) {
    const auto img = io::read_image(std::string(EPONA_TEST_DATA_DIR) + "/demo/frame_0" + std::to_string(i % 3) + ".png");
    frames.push_back(io::resize_bicubic(img, w.image_h, w.image_w));
    poses.x.push_back(2.0f), poses.y.push_back(0.1f), poses.yaw.push_back(0.5f);
  }
  std::ostringstream sink;
  cpu::Context ctx;
  return model::make_window(ctx, app::encode_frames(e, frames, app::Console{sink, sink, true, false}), poses);
}

}  // namespace

TEST_CASE("CUDA engine, float32: encode, decode, plan and rollout steps match the CPU engine") {
  EPONA_REQUIRE_GPU();
  const auto files = golden_files();
  const auto& w = files.configs.world;
  auto cpu_engine = loaded("cpu", false, files);
  auto gpu_engine = loaded("cuda", false, files);

  const History h_cpu = window_of(*cpu_engine, w), h_gpu = window_of(*gpu_engine, w);
  CHECK(rel_max(h_gpu.latents, h_cpu.latents) <= 1e-4);

  cpu::Context ctx;
  const Tensor<float> z = tokens_to_latent(ctx, h_cpu.latents.reshape({w.condition_frames, w.img_tokens(), w.token_dim()}),
                                           w.latent_h(), w.latent_w());
  CHECK(rel_max(gpu_engine->decode(z, false), cpu_engine->decode(z, false)) <= 1e-4);
  const std::int64_t clip = files.configs.dcae.condition_frames;
  if (files.configs.dcae.add_decoder_temporal && z.size(0) >= clip)
    CHECK(rel_max(gpu_engine->decode(z.slice(0, clip), true), cpu_engine->decode(z.slice(0, clip), true)) <= 1e-4);

  SampleOptions opt;
  opt.seed = 5;
  opt.steps = 3;
  CHECK(rel_max(gpu_engine->plan(h_cpu, opt), cpu_engine->plan(h_cpu, opt)) <= 1e-4);

  NoiseSource n_cpu = NoiseSource::seeded(9), n_gpu = NoiseSource::seeded(9);
  History a = h_cpu, b = h_cpu;
  for (int s = 0; s < 2; ++s) {
    const StepResult rc = cpu_engine->step(a, nullptr, 3, n_cpu);
    const StepResult rg = gpu_engine->step(b, nullptr, 3, n_gpu);
    CHECK(rel_max(rg.trajectory, rc.trajectory) <= 1e-3);
    CHECK(rel_max(rg.latent, rc.latent) <= 1e-3);
    model::slide_window(a, rc.latent, rc.trajectory);
    model::slide_window(b, rg.latent, rg.trajectory);
  }
}

TEST_CASE("CUDA engine, bf16: runs end to end with finite results") {
  EPONA_REQUIRE_GPU();
  const auto files = golden_files();
  const auto& w = files.configs.world;
  auto gpu_engine = loaded("cuda", true, files);
  const History h = window_of(*gpu_engine, w);
  CHECK(all_finite(h.latents));
  SampleOptions opt;
  opt.steps = 2;
  const Tensor<float> plan = gpu_engine->plan(h, opt);
  CHECK(plan.shape() == Shape{1, w.traj_len, 3});
  CHECK(all_finite(plan));
  NoiseSource noise = NoiseSource::seeded(0);
  const StepResult r = gpu_engine->step(h, nullptr, 2, noise);
  CHECK(all_finite(r.latent));
  cpu::Context ctx;
  const Tensor<float> images =
      gpu_engine->decode(tokens_to_latent(ctx, r.latent, w.latent_h(), w.latent_w()), false);
  CHECK(images.shape() == Shape{1, 3, w.image_h, w.image_w});
  CHECK(all_finite(images));
}

TEST_CASE("CUDA engine, float32: plan hypotheses match the CPU engine's, and hypothesis k its seed's plan") {
  EPONA_REQUIRE_GPU();
  const auto files = golden_files();
  auto cpu_engine = loaded("cpu", false, files);
  auto gpu_engine = loaded("cuda", false, files);
  const History h = window_of(*cpu_engine, files.configs.world);
  SampleOptions opt;
  opt.seed = 5;
  opt.steps = 3;
  const std::int64_t K = 6;
  auto& model_engine = dynamic_cast<app::ModelEngine<Cuda, float>&>(*gpu_engine);
  const auto poison = [&](bool on) {  // scratch handed out as NaN: an unwritten element shows
    model_engine.configure_contexts([on](cuda::Context& ctx) { ctx.policy().poison_new_buffers = on; });
  };
  poison(true);
  const Tensor<float> gpu = gpu_engine->plan_hypotheses(h, K, opt);
  poison(false);
  CHECK(gpu.shape() == Shape{K, files.configs.world.traj_len, 3});
  CHECK(all_finite(gpu));
  CHECK(rel_max(gpu, cpu_engine->plan_hypotheses(h, K, opt)) <= 1e-4);
  SampleOptions last = opt;
  last.seed = WorldModel<Cpu, float>::hypothesis_seed(opt.seed, K - 1);
  CHECK(rel_max(gpu.slice(K - 1, K), gpu_engine->plan(h, last)) <= 1e-4);
}

// The one translation unit of this program that compiles stb (after every other include).
#include "epona/io/stb_implementation.hpp"

namespace {
class KeptFrames final : public app::FrameConsumer {
 public:
  void put(const io::Image& img) override { frames.push_back(img); }
  std::vector<io::Image> frames;
};
}  // namespace

// The rollout decodes each clip on a worker thread while the next steps sample (issue #40): its
// frames must be, in order and bit for bit, the latents it kept decoded afterwards on the main thread.
TEST_CASE("CUDA engine: a rollout's frames decoded beside its steps equal its latents decoded after it") {
  EPONA_REQUIRE_GPU();
  const auto files = golden_files();
  const auto& w = files.configs.world;
  auto engine = loaded("cuda", false, files);
  REQUIRE(engine->decodes_beside_steps());
  const History h = window_of(*engine, w);
  const std::int64_t clip = files.configs.dcae.add_decoder_temporal ? files.configs.dcae.condition_frames : 1;
  app::RolloutPlan plan;
  plan.frames = 2 * clip + 1;  // two whole clips and a last frame alone
  plan.clip_len = clip;
  plan.samplers = DitSamplers::euler(2);
  plan.seed = 3;
  plan.keep_latents = true;
  KeptFrames kept;
  std::ostringstream sink;
  cpu::Context ctx;
  const app::RolloutLog log = app::roll_out(*engine, ctx, h, w, plan, kept, app::Console{sink, sink, true, false});
  REQUIRE(kept.frames.size() == std::size_t(plan.frames));
  std::size_t next = 0;
  for (std::int64_t first = 0; first < plan.frames; first += clip) {
    const std::int64_t n = std::min(clip, plan.frames - first);
    const Tensor<float> z = tokens_to_latent(ctx, log.latents.slice(first, first + n), w.latent_h(), w.latent_w());
    const Tensor<float> images = engine->decode(z, n == clip && clip > 1);
    for (std::int64_t i = 0; i < n; ++i, ++next) {
      const io::Image expected = io::tensor_to_image(images, i);
      CHECK_MESSAGE(kept.frames[next].rgb == expected.rgb, "frame ", next);
    }
  }
}
