// Shared by the tests that run the whole world model on the golden set: the model loaded once
// from its weights, and the golden window (the MST case's latents and the first F motions).
#pragma once

#include "epona/model/world_model.hpp"
#include "world_golden.hpp"

namespace epona::test {

inline WorldModel<Cpu, float>& golden_world_model() {
  static auto m = WorldModel<Cpu, float>::load(world_golden().weights, world_golden().world());
  return m;
}

inline History golden_history() {
  const auto& g = world_golden();
  const std::int64_t F = g.world().condition_frames;
  return {g.tensor("mst.latents"), first_entries(g.tensor("mst.rel_pose"), F), first_entries(g.tensor("mst.rel_yaw"), F)};
}

}  // namespace epona::test
