// apps/epona/bundled_model.hpp — where the model and clip used without --weights live: the
// program's bundled model, or in test programs the conformance model. Apart from models.hpp so that
// tests can name the bundled files without compiling the loaders.
#pragma once

#include <cstdlib>
#include <string>

namespace epona::app {

// Where the bundled data lives: $EPONA_DATA_DIR, else the source tree's tests/data as built in.
inline std::string data_dir() {
  if (const char* env = std::getenv("EPONA_DATA_DIR"); env && *env) return env;
#if defined(EPONA_APP_DATA_DIR)
  return EPONA_APP_DATA_DIR;
#elif defined(EPONA_TEST_DATA_DIR)
  return EPONA_TEST_DATA_DIR;
#else
  return "tests/data";
#endif
}

// The model and clip used without --weights. The program: the small Epona trained on the synthetic
// world (models/small-synthetic, docs/training.md) and its held-out demo clip. Test programs, built
// without EPONA_APP_MODEL_DIR: the conformance model of tests/data/golden and the 3-frame clip of
// tests/data/demo (fast and exact). $EPONA_MODEL_DIR names another folder of the same layout
// (configs.json, weights_world/_dcae.safetensors, demo/frames/ + demo/poses.csv).
struct BundledModel {
  std::string dir;            // configs.json + weights
  std::string frames, poses;  // the demo clip
  bool trained;               // false: random conformance weights
};

inline BundledModel bundled_model() {
  const auto trained_layout = [](const std::string& dir) { return BundledModel{dir, dir + "/demo/frames", dir + "/demo/poses.csv", true}; };
  if (const char* env = std::getenv("EPONA_MODEL_DIR"); env && *env) return trained_layout(env);
#if defined(EPONA_APP_MODEL_DIR)
  if (!std::getenv("EPONA_DATA_DIR")) return trained_layout(EPONA_APP_MODEL_DIR);
#endif
  return {data_dir() + "/golden", data_dir() + "/demo", data_dir() + "/demo/poses.csv", false};
}
inline std::string demo_model_dir() { return bundled_model().dir; }
inline std::string demo_frames_dir() { return bundled_model().frames; }
inline std::string demo_poses_file() { return bundled_model().poses; }
inline const char* demo_description() {
  return bundled_model().trained ? " (bundled: the small Epona trained on the synthetic world)"
                                 : " (bundled demo: small random conformance weights)";
}

}  // namespace epona::app
