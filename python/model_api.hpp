// python/model_api.hpp — the operations the `epona` Python module runs on a loaded model, behind
// one interface of host tensors, whatever the backend and weight type: the pybind11 code is
// written once, in plain C++, and only the CUDA instantiation (python/cuda_model.cu, compiled by
// nvcc when the build has CUDA) needs the CUDA compiler — as the CLI's Engine does
// (apps/epona/engine.hpp). ModelOf<B, W> (python/model_of.hpp) implements it over the library's
// WorldModel<B, W>, Dcae<B, W> and WorldSession<B, W>. No pybind11 and no CUDA header here.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/cpu/context.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/world_session.hpp"
#include "epona/io/image.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "epona/models.hpp"

namespace epona::python {

// A WorldSession on a loaded model (see epona/domain/world_session.hpp).
class SessionApi {
 public:
  virtual ~SessionApi() = default;
  virtual void reset(const std::vector<io::Image>& frames, const io::PoseSequence& poses) = 0;
  virtual SessionStep step(const std::optional<Motion>& action) = 0;
  virtual const History& window() const = 0;  // on the host, whatever the backend
  virtual std::int64_t steps_taken() const = 0;
  virtual std::size_t arena_capacity() const = 0;
};

class ModelApi {
 public:
  virtual ~ModelApi() = default;
  virtual const WorldModelConfig& config() const = 0;
  virtual const char* backend() const = 0;  // "cpu" or "cuda"
  virtual const char* dtype() const = 0;    // the weights': "float32" or "bfloat16"
  // The host context of the latent layout changes (tokens <-> NCHW) and windows: on the CPU the
  // model's own (its threads).
  virtual cpu::Context& host() = 0;

  // 8-bit RGB frames -> latents (N, C, h, w), batched as Dcae::encode takes them.
  virtual Tensor<float> encode(const std::vector<io::Image>& frames) = 0;
  // Latents (N, C, h, w) -> 8-bit RGB images; `video`: the temporal decoder over clips.
  virtual std::vector<io::Image> decode(const Tensor<float>& latents, bool video) = 0;
  // WorldModel::plan (K = 1, the official path) or plan_hypotheses: (K, traj_len, 3).
  virtual Tensor<float> plans(const History& window, std::int64_t K, const SampleOptions& opt) = 0;
  virtual StepResult predict_next(const History& window, const std::optional<NextAction>& action,
                                  const SampleOptions& opt) = 0;
  virtual RolloutResult rollout(const History& window, const RolloutOptions& opt) = 0;
  // A session over this model: it refers to the model, which must outlive it.
  virtual std::unique_ptr<SessionApi> session(const SampleOptions& opt) = 0;
};

// Defined in python/cuda_model.cu (nvcc) when the module is built with CUDA (EPONA_PYTHON_CUDA):
// the model on the GPU with float32 or bf16 weights (c.bf16_weights), or an epona::Error saying
// why not (no GPU). cuda_device_present(): a CUDA device can be used (cuda::has_gpu()).
#if defined(EPONA_PYTHON_CUDA)
std::unique_ptr<ModelApi> make_cuda_model(const app::ModelFiles& files, const app::ComputeOptions& c,
                                          const app::Console& con);
bool cuda_device_present();
#endif

}  // namespace epona::python
