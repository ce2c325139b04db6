// epona/epona.hpp — the umbrella header: the CPU backend, the readers, the models (MST,
// TrajDiT/VisDiT, DC-AE with its temporal decoder), the samplers and the world-model API.
// The CUDA backend is added by including epona/cuda/backend.cuh from a .cu file; the stb
// implementation by including epona/io/stb_implementation.hpp in exactly one source file.
#pragma once

#include "epona/core/arena.hpp"
#include "epona/core/backend.hpp"
#include "epona/core/dtype.hpp"
#include "epona/core/env.hpp"
#include "epona/core/error.hpp"
#include "epona/core/kernel_options.hpp"
#include "epona/core/rng.hpp"
#include "epona/core/tensor.hpp"

#include "epona/cpu/ops.hpp"

#include "epona/flow/euler.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"

#include "epona/io/image.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/npy.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/io/torch_checkpoint.hpp"
// epona/io/video_writer.hpp is left out: it needs FFmpeg's libraries (CMake: epona_ffmpeg).

#include "epona/model/config.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/parameter_counts.hpp"
#include "epona/model/plan_choice.hpp"
#include "epona/model/relative_pose.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"

#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "epona/domain/world_session.hpp"
