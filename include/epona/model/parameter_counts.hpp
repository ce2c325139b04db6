// epona/model/parameter_counts.hpp — parameter counts of a configuration and its model-size
// check, both from the parameter tree (nn/parameter.hpp): the layers' skeleton, built from the
// config without weights, lists every parameter once; counts are sums over its prefixes. Above
// the configs (model/config/) and the models, which the configs cannot include.
#pragma once

#include "epona/core/backend.hpp"
#include "epona/model/config/dcae_config.hpp"
#include "epona/model/config/world_config.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/world_model.hpp"
#include "epona/nn/parameter.hpp"

namespace epona::model {

// The parameters of a configuration (names and shapes in visiting order; the official prefixes).
// The config is validated (the world model's but for what shapes no parameter, its RoPE split),
// its sizes are not (validate_with_size).
inline nn::ParamList world_parameter_list(const WorldModelConfig& c) { return WorldModel<Cpu, float>::parameter_list(c); }
inline nn::ParamList dcae_parameter_list(const DcaeConfig& c) { return Dcae<Cpu, float>::parameter_list(c); }

// Learnable values of each network of the world model (module.model., module.dit., module.traj_dit.).
struct WorldParameterCounts {
  double mst = 0, vis_dit = 0, traj_dit = 0, total = 0;
};
inline WorldParameterCounts world_parameter_counts(const WorldModelConfig& c) {
  const nn::ParamList list = world_parameter_list(c);
  return {list.count("module.model."), list.count("module.dit."), list.count("module.traj_dit."), list.count()};
}

// Learnable values of each part of the DC-AE (encoder., decoder., the temporal front's
// causal_time_block. and space_block.) and its BatchNorm buffers (stored, not learned).
struct DcaeParameterCounts {
  double encoder = 0, decoder = 0, time_blocks = 0, space_blocks = 0, total = 0, buffers = 0;
  double temporal() const { return time_blocks + space_blocks; }
};
inline DcaeParameterCounts dcae_parameter_counts(const DcaeConfig& c) {
  const nn::ParamList list = dcae_parameter_list(c);
  return {list.learned_count("encoder."),          list.learned_count("decoder."),
          list.learned_count("causal_time_block."), list.learned_count("space_block."),
          list.learned_count(),                     list.buffer_count()};
}

// validate() and the size limits (what WorldModel::load and Dcae's constructor check): throws
// one error naming every problem, the parameter count past the limit among them.
inline void validate_with_size(const WorldModelConfig& c) {
  c.validate();
  c.check_size(world_parameter_counts(c).total);
}
inline void validate_with_size(const DcaeConfig& c) { c.check_size(dcae_parameter_counts(c).total); }

}  // namespace epona::model
