// Shared by the world-model golden tests: the golden set (EPONA_GOLDEN_DIR, default the copy
// in tests/data/golden) loaded once — world weights, cases, configs.json — and the checks
// against it, in the metric of tests/metrics.hpp (rel_max).
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "../golden_dir.hpp"
#include "../metrics.hpp"
#include "epona/core/tensor.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/io/tensor_map.hpp"

namespace epona::test {

struct WorldGolden {
  io::TensorMap weights, cases;
  io::ModelConfigs configs;

  bool has(const std::string& name) const { return cases.contains(name); }
  Tensor<float, Cpu> tensor(const std::string& name) const { return io::to_tensor<float>(cases.at(name)); }
  const WorldModelConfig& world() const { return configs.world; }
};

// The world-model weights: $EPONA_WORLD_WEIGHTS (a .safetensors or an official-format .pkl, so
// the same parity checks run on weights read by the checkpoint loader), else the golden file.
inline std::string world_weights_path() {
  const char* env = std::getenv("EPONA_WORLD_WEIGHTS");
  return env && *env ? std::string(env) : golden_dir() + "/weights_world.safetensors";
}

inline const WorldGolden& world_golden() {
  static const WorldGolden g{io::load_weights(world_weights_path()),
                             io::load_safetensors(golden_dir() + "/cases.safetensors"),
                             io::load_configs(golden_dir() + "/configs.json")};
  return g;
}

// Tolerances of the golden README for the float32 path.
inline double golden_tolerance(const std::string& name) {
  const auto starts = [&](const char* p) { return name.rfind(p, 0) == 0; };
  if (starts("ids.") || starts("sched.") || starts("tok.") || name == "mst.pose_idx" || name == "mst.yaw_idx")
    return 1e-6;
  if (starts("rollout.")) return 1e-3;
  return 1e-4;
}

// Compares with the golden tensor `name` (same shape required) and prints the figure.
inline void expect_golden(const std::string& name, const Tensor<float, Cpu>& ours, const std::string& note = "") {
  const auto golden = world_golden().tensor(name);
  REQUIRE_MESSAGE(ours.shape() == golden.shape(), name, ": ours ", shape_str(ours.shape()), ", golden ",
                  shape_str(golden.shape()));
  const double rel = rel_max(ours, golden), tol = golden_tolerance(name);
  MESSAGE(name, note, ": rel ", rel, " (limit ", tol, ")");
  CHECK_MESSAGE(rel <= tol, name, ": rel ", rel, " exceeds ", tol);
}

// The first `n` entries along dim 1 of a (B, N, k) tensor.
inline Tensor<float, Cpu> first_entries(const Tensor<float, Cpu>& t, std::int64_t n) {
  Tensor<float, Cpu> out({t.size(0), n, t.size(2)});
  for (std::int64_t b = 0; b < t.size(0); ++b) std::copy_n(t[b].data(), n * t.size(2), out[b].data());
  return out;
}

// Per-step tensors stacked into (S, ...), `shape` per step.
struct Stack {
  Tensor<float, Cpu> t;
  Stack(std::int64_t steps, Shape shape) {
    shape.insert(shape.begin(), steps);
    t = Tensor<float, Cpu>(shape);
  }
  void put(std::int64_t s, const Tensor<float, Cpu>& x) {
    REQUIRE(x.numel() == t[s].numel());
    std::copy_n(x.data(), x.numel(), t[s].data());
  }
};

}  // namespace epona::test
