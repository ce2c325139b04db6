// epona/model/config.hpp — the umbrella of the model's configuration: the official constants
// (config/constants.hpp), the world model's (config/world_config.hpp) and the DC-AE's
// (config/dcae_config.hpp) hyper-parameters with their validate(). Parameter counts and the
// model-size check come from the parameter tree: model/parameter_counts.hpp.
#pragma once

#include "epona/model/config/constants.hpp"
#include "epona/model/config/dcae_config.hpp"
#include "epona/model/config/problems.hpp"
#include "epona/model/config/world_config.hpp"
