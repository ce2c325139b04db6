// example_plan — Epona as a motion planner, through the library API: load the world model and
// the DC-AE, encode the last F frames of a clip, and plan the next traj_len waypoints (15 = 3 s at
// 5 Hz for the released model) from them and the ego motion into each frame.
//
// usage: example_plan [MODEL_DIR [CLIP_DIR]]     (run from the repository root)
//   MODEL_DIR  configs.json, weights_world.safetensors, weights_dcae.safetensors
//              (default tests/data/golden: the small conformance model, random weights)
//   CLIP_DIR   frames (*.png, in name order) and poses.csv with one x,y,yaw row per frame
//              (default tests/data/demo)
// The released model: io::load_weights("world.pkl") / ("dcae_td_20000.pkl") with the
// default-constructed WorldModelConfig{} and DcaeConfig{}.
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
#include "epona/model/world_model.hpp"

using namespace epona;

int main(int argc, char** argv) {
  const std::string model_dir = argc > 1 ? argv[1] : "tests/data/golden";
  const std::string clip_dir = argc > 2 ? argv[2] : "tests/data/demo";
  try {
    const io::ModelConfigs cfg = io::load_configs(model_dir + "/configs.json");
    const auto dcae = Dcae<Cpu, float>::load(io::load_weights(model_dir + "/weights_dcae.safetensors"), cfg.dcae);
    auto world = WorldModel<Cpu, float>::load(io::load_weights(model_dir + "/weights_world.safetensors"), cfg.world);
    const std::int64_t F = cfg.world.condition_frames;

    // The last F frames at the model's size, and the motion into each (x m forward, y m left, yaw deg).
    std::vector<std::filesystem::path> files;
    for (const auto& e : std::filesystem::directory_iterator(clip_dir))
      if (e.path().extension() == ".png") files.push_back(e.path());
    std::sort(files.begin(), files.end());
    const io::PoseSequence all_poses = io::load_poses(clip_dir + "/poses.csv");
    EPONA_CHECK(std::int64_t(files.size()) >= F && all_poses.size() == files.size(), clip_dir, ": need at least ", F,
                " frames and one pose per frame");
    std::vector<io::Image> frames;
    io::PoseSequence poses;
    for (std::size_t i = files.size() - std::size_t(F); i < files.size(); ++i) {
      frames.push_back(io::read_image(files[i].string(), {.height = cfg.world.image_h, .width = cfg.world.image_w,
                                                          .size = io::SizePolicy::Resize}));
      poses.x.push_back(all_poses.x[i]), poses.y.push_back(all_poses.y[i]), poses.yaw.push_back(all_poses.yaw[i]);
    }

    // DC-AE latents (F, C, h, w) -> the world model's tokens (1, F, L, C).
    cpu::Context ctx;
    const Tensor<float> tokens = latent_to_tokens(ctx, dcae.encode(ctx, io::images_to_tensor(frames)));
    const History window{tokens.reshape({1, F, tokens.size(1), tokens.size(2)}), poses.pose_tensor(), poses.yaw_tensor()};

    SampleOptions sampling;
    sampling.seed = 0;  // steps: the configuration's num_sampling_steps
    const Tensor<float> plan = world.plan(window, sampling);  // (1, traj_len, 3)
    std::printf("planned trajectory (ego frame of the last frame):\n  waypoint   x (m)    y (m)  yaw (deg)\n");
    for (std::int64_t i = 0; i < plan.size(1); ++i)
      std::printf("  %8lld %7.2f  %7.2f  %8.2f\n", static_cast<long long>(i), plan.at(0, i, 0), plan.at(0, i, 1),
                  plan.at(0, i, 2));
    return 0;
  } catch (const Error& e) {
    std::fprintf(stderr, "example_plan: error: %s\n", e.what());
    return 1;
  }
}

// stb is compiled in exactly one translation unit, after every other include.
#include "epona/io/stb_implementation.hpp"
