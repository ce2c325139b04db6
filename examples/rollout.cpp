// example_rollout — Epona as a driving-world simulator, through the library API: from the last
// F frames of a clip, roll out N new frames, each step driven by the model's own plan (waypoint 0,
// as the official test_free.py) or, with --straight, by a given action (2 m forward per frame);
// then decode the latents with the DC-AE's temporal decoder and save them as PNG.
//
// usage: example_rollout [--straight] [N [MODEL_DIR [CLIP_DIR [OUT_DIR]]]]   (from the repository root)
//   defaults: N = 4, tests/data/golden (conformance model, random weights), tests/data/demo,
//   out/example_rollout
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "epona/cpu/context.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/io/image.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"

using namespace epona;

namespace {

// The window the model starts from: the last F frames of a clip, encoded, and their motions.
History clip_window(cpu::Context& ctx, const Dcae<Cpu, float>& dcae, const WorldModelConfig& w, const std::string& dir) {
  std::vector<std::filesystem::path> files;
  for (const auto& e : std::filesystem::directory_iterator(dir))
    if (e.path().extension() == ".png") files.push_back(e.path());
  std::sort(files.begin(), files.end());
  const io::PoseSequence all = io::load_poses(dir + "/poses.csv");
  const std::int64_t F = w.condition_frames;
  EPONA_CHECK(std::int64_t(files.size()) >= F && all.size() == files.size(), dir, ": need at least ", F,
              " frames and one pose per frame");
  std::vector<io::Image> frames;
  io::PoseSequence poses;
  for (std::size_t i = files.size() - std::size_t(F); i < files.size(); ++i) {
    frames.push_back(io::read_image(files[i].string(), {.height = w.image_h, .width = w.image_w,
                                                        .size = io::SizePolicy::Resize}));
    poses.x.push_back(all.x[i]), poses.y.push_back(all.y[i]), poses.yaw.push_back(all.yaw[i]);
  }
  const Tensor<float> tokens = latent_to_tokens(ctx, dcae.encode(ctx, io::images_to_tensor(frames)));  // (F, L, C)
  return {tokens.reshape({1, F, tokens.size(1), tokens.size(2)}), poses.pose_tensor(), poses.yaw_tensor()};
}

// Decodes latent tokens (N, L, C) in clips of the DC-AE's temporal length (the rest frame by frame,
// as test_nuplan.py) and writes out/frame_NN.png.
void save_frames(cpu::Context& ctx, const Dcae<Cpu, float>& dcae, const WorldModelConfig& w, const Tensor<float>& tokens,
                 const std::filesystem::path& out) {
  std::filesystem::create_directories(out);
  const Tensor<float> latents = tokens_to_latent(ctx, tokens, w.latent_h(), w.latent_w());  // (N, C, h, w)
  const std::int64_t N = latents.size(0), clip = dcae.config().condition_frames;
  for (std::int64_t first = 0; first < N;) {
    const std::int64_t n = first + clip <= N ? clip : 1;
    const Tensor<float> images = dcae.decode(ctx, latents.slice(first, first + n), n > 1);  // (n, 3, H, W)
    for (std::int64_t i = 0; i < n; ++i) {
      char name[32];
      std::snprintf(name, sizeof name, "frame_%02lld.png", static_cast<long long>(first + i));
      io::save_png((out / name).string(), images, i);
    }
    first += n;
  }
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> args(argv + 1, argv + argc);
  const bool straight = !args.empty() && args[0] == "--straight";
  if (straight) args.erase(args.begin());
  const std::int64_t N = args.size() > 0 ? std::stoll(args[0]) : 4;
  const std::string model_dir = args.size() > 1 ? args[1] : "tests/data/golden";
  const std::string clip_dir = args.size() > 2 ? args[2] : "tests/data/demo";
  const std::string out = args.size() > 3 ? args[3] : "out/example_rollout";
  try {
    const io::ModelConfigs cfg = io::load_configs(model_dir + "/configs.json");
    const auto dcae = Dcae<Cpu, float>::load(io::load_weights(model_dir + "/weights_dcae.safetensors"), cfg.dcae);
    auto world = WorldModel<Cpu, float>::load(io::load_weights(model_dir + "/weights_world.safetensors"), cfg.world);
    cpu::Context ctx;
    History window = clip_window(ctx, dcae, cfg.world, clip_dir);
    Tensor<float> tokens({N, cfg.world.img_tokens(), cfg.world.token_dim()});

    if (!straight) {  // self-predicted: one call, the window slides inside
      RolloutOptions opt;
      opt.frames = N;
      opt.sample.seed = 0;
      const RolloutResult r = rollout(world, window, opt, [](const RolloutFrame<Cpu>& f) {
        std::printf("frame %lld: drove x %.2f m, y %.2f m, yaw %.2f deg (waypoint 0 of its plan)\n",
                    static_cast<long long>(f.index), f.result.trajectory.at(0, 0, 0), f.result.trajectory.at(0, 0, 1),
                    f.result.trajectory.at(0, 0, 2));
      });
      std::copy_n(r.latents.data(), tokens.numel(), tokens.data());  // (N, 1, L, C) -> (N, L, C)
    } else {  // given actions: predict_next, then slide the window by hand
      NextAction forward{Tensor<float>::full({1, 1, 2}, 0.0f), Tensor<float>::zeros({1, 1, 1})};
      forward.rel_pose.at(0, 0, 0) = 2.0f;  // metres forward per frame
      for (std::int64_t i = 0; i < N; ++i) {
        SampleOptions sampling;
        sampling.seed = static_cast<std::uint64_t>(i);  // fresh noise each step
        const StepResult step = world.predict_next(window, forward, sampling);
        Tensor<float> action({1, 1, 3});
        action.at(0, 0, 0) = 2.0f, action.at(0, 0, 1) = 0.0f, action.at(0, 0, 2) = 0.0f;
        model::slide_window(window, step.latent, action);
        std::copy_n(step.latent.data(), step.latent.numel(), tokens[i].data());
        std::printf("frame %lld: drove 2 m straight ahead\n", static_cast<long long>(i));
      }
    }
    save_frames(ctx, dcae, cfg.world, tokens, out);
    std::printf("wrote %lld frame(s) of %lldx%lld to %s/\n", static_cast<long long>(N),
                static_cast<long long>(cfg.world.image_h), static_cast<long long>(cfg.world.image_w), out.c_str());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "example_rollout: error: %s\n", e.what());
    return 1;
  }
}

// stb is compiled in exactly one translation unit, after every other include.
#include "epona/io/stb_implementation.hpp"
