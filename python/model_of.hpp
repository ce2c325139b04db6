// python/model_of.hpp — ModelApi (python/model_api.hpp) over the library's WorldModel<B, W> and
// Dcae<B, W>, loaded by the CLI's loaders (apps/epona/models.hpp), and SessionApi over
// WorldSession<B, W>. Host tensors in and out: images and latents cross to the backend's memory
// only around the DC-AE (the WorldModel's interface is on the host already). The DC-AE runs on the
// world model's context, as WorldSession does. For B = Cuda include epona/cuda/backend.cuh first
// (python/cuda_model.cu does).
#pragma once

#include <memory>
#include <optional>
#include <type_traits>
#include <utility>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/nn/backend_context.hpp"
#include "model_api.hpp"

namespace epona::python {

template <class B, class W>
class SessionOf final : public SessionApi {
 public:
  SessionOf(WorldModel<B, W>& world, const Dcae<B, W>& dcae, const SampleOptions& opt) : session_(world, dcae, opt) {}
  void reset(const std::vector<io::Image>& frames, const io::PoseSequence& poses) override {
    session_.reset(frames, poses);
  }
  SessionStep step(const std::optional<Motion>& action) override { return session_.step(action); }
  const History& window() const override { return session_.window(); }
  std::int64_t steps_taken() const override { return session_.steps_taken(); }
  std::size_t arena_capacity() const override { return session_.arena_capacity(); }

 private:
  WorldSession<B, W> session_;
};

template <class B, class W>
class ModelOf final : public ModelApi {
 public:
  // `keep` is released after the models (the CUDA model's hold on the process-wide cuDNN handles).
  ModelOf(const app::ModelFiles& files, const app::ComputeOptions& c, const app::Console& con,
          std::shared_ptr<void> keep = nullptr)
      : keep_(std::move(keep)), host_(make_host_context(c)), dcae_(app::load_dcae<B, W>(files, con)),
        world_(app::load_world<B, W>(files, c, con)) {}

  const WorldModelConfig& config() const override { return world_.config(); }
  const char* backend() const override { return std::is_same_v<B, Cpu> ? "cpu" : "cuda"; }
  const char* dtype() const override { return std::is_same_v<W, bf16> ? "bfloat16" : "float32"; }
  cpu::Context& host() override {
    if constexpr (std::is_same_v<B, Cpu>)
      return world_.context();
    else
      return *host_;
  }

  Tensor<float> encode(const std::vector<io::Image>& frames) override {
    const Tensor<float, B> images = BackendTraits<B>::upload(io::images_to_tensor(frames));
    return host_tensor(ctx(), dcae_.encode(ctx(), images));
  }
  std::vector<io::Image> decode(const Tensor<float>& latents, bool video) override {
    const Tensor<float> x = host_tensor(ctx(), dcae_.decode(ctx(), BackendTraits<B>::upload(latents), video));
    std::vector<io::Image> images;
    for (std::int64_t i = 0; i < x.size(0); ++i) images.push_back(io::tensor_to_image(x, i));
    return images;
  }
  Tensor<float> plans(const History& window, std::int64_t K, const SampleOptions& opt) override {
    return K == 1 ? world_.plan(window, opt) : world_.plan_hypotheses(window, K, opt);
  }
  StepResult predict_next(const History& window, const std::optional<NextAction>& action,
                          const SampleOptions& opt) override {
    return world_.predict_next(window, action, opt);
  }
  RolloutResult rollout(const History& window, const RolloutOptions& opt) override {
    return model::rollout(world_, window, opt);
  }
  std::unique_ptr<SessionApi> session(const SampleOptions& opt) override {
    return std::make_unique<SessionOf<B, W>>(world_, dcae_, opt);
  }

 private:
  // A device backend's host work (layouts, windows) gets a context of its own with the load's
  // thread count; on the CPU the world model's context is the host's.
  static std::unique_ptr<cpu::Context> make_host_context(const app::ComputeOptions& c) {
    if constexpr (std::is_same_v<B, Cpu>)
      return nullptr;
    else
      return std::make_unique<cpu::Context>(c.threads);
  }
  BackendContext<B>& ctx() { return world_.context(); }

  std::shared_ptr<void> keep_;  // first member: released after the models
  std::unique_ptr<cpu::Context> host_;
  Dcae<B, W> dcae_;
  WorldModel<B, W> world_;
};

}  // namespace epona::python
