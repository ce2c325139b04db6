// epona/model/random_weights.hpp — a world-model weight map with random values under every
// official key (docs/checkpoints.md: `module.model.`, `module.dit.`, `module.traj_dit.`),
// sized from a WorldModelConfig: for benchmarks and examples at any size without a checkpoint.
// The names and shapes are the parameter tree's (WorldModel::parameter_list), the values
// nn::RandomValues' under WeightInit::torch_linear (matrices ~ U(±1/sqrt(fan_in)), as PyTorch
// initialises the official nn.Linear layers; norm scales near 1, biases near 0).
#pragma once

#include <cstdint>

#include "epona/io/tensor_map.hpp"
#include "epona/model/config/world_config.hpp"
#include "epona/model/world_model.hpp"

namespace epona::model {

// Throws (as WorldModel::load would) for a configuration that does not validate or is too large.
inline io::TensorMap random_world_weights(const WorldModelConfig& c, std::uint64_t seed = 1) {
  c.validate();
  const nn::ParamList list = WorldModel<Cpu, float>::parameter_list(c);
  c.check_size(list.count());
  return list.random_map(seed, "random world weights", nn::WeightInit::torch_linear);
}

}  // namespace epona::model
