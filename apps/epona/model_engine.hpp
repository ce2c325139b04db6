// apps/epona/model_engine.hpp — the models a command runs, on the backend and weight type the user
// chose, behind one interface of host tensors (Engine): the commands are written once, and only
// the CUDA instantiation (apps/epona/cuda_engine.cu, compiled by nvcc when the build has CUDA)
// needs the CUDA compiler. ModelEngine<B, W> holds a WorldModel<B, W> and a Dcae<B, W>; with a
// VisShard its VisDiT is one shard of a tensor-parallel group (sharded_engine.hpp). make_engine
// (engine.hpp) picks one.
#pragma once

#include <functional>
#include <memory>
#include <optional>
#include <type_traits>

#include "console.hpp"
#include "models.hpp"
#include "epona/core/tensor.hpp"
#include "epona/io/image.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/world_model.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona::app {

class Engine {
 public:
  virtual ~Engine() = default;
  virtual void load_dcae(const ModelFiles& f, const Console& con) = 0;
  virtual void load_world(const ModelFiles& f, const Console& con) = 0;
  virtual void release_dcae() = 0;  // frees its memory (plan needs the DC-AE only to encode)
  virtual const DcaeConfig& dcae_config() const = 0;

  // One frame (8-bit RGB) -> its latent (1, C, H/32, W/32), on the host.
  virtual Tensor<float> encode(const io::Image& frame) = 0;
  // Latents (N, C, h, w) -> images (N, 3, 32h, 32w) in the model's [-1, 1] range, on the host.
  virtual Tensor<float> decode(const Tensor<float>& latents, bool is_video) = 0;
  // Whether decode may run on another thread while step runs: the DC-AE and the world model have
  // contexts (GPU streams) of their own. Not on the CPU, where both would share the cores.
  virtual bool decodes_beside_steps() const = 0;
  // WorldModel::plan and WorldModel::run_step (one step drawing from `noise`; want_latent = true).
  virtual Tensor<float> plan(const History& window, const SampleOptions& opt) = 0;
  // WorldModel::plan_hypotheses: K plans of one scene (K, traj_len, 3).
  virtual Tensor<float> plan_hypotheses(const History& window, std::int64_t K, const SampleOptions& opt) = 0;
  // K plans (K, traj_len, 3); one is plan() itself, the official path.
  Tensor<float> plans(const History& window, std::int64_t K, const SampleOptions& opt) {
    return K > 1 ? plan_hypotheses(window, K, opt) : plan(window, opt);
  }
  virtual StepResult step(const History& window, const NextAction* action, const DitSamplers& samplers,
                          NoiseSource& noise) = 0;
  // The official sampler: `steps` Euler steps for both DiTs.
  StepResult step(const History& window, const NextAction* action, std::int64_t steps, NoiseSource& noise) {
    return step(window, action, DitSamplers::euler(steps), noise);
  }
};

template <class B, class W>
class ModelEngine final : public Engine {
 public:
  using VisShard = typename WorldModel<B, W>::VisShard;
  explicit ModelEngine(const ComputeOptions& c, const VisShard& shard = {})
      : compute_(c), shard_(shard), ctx_(make_context(c)) {}

  // `fn` runs when the engine is destroyed, after the models and their context (the CUDA
  // engine releases the process-wide cuDNN handles there).
  void after_destruction(std::function<void()> fn) { after_destruction_.fn = std::move(fn); }
  // `fn` runs on each of the engine's contexts: the DC-AE's now, the world model's now or when it
  // is loaded (the CUDA engine sets its kernel policy there).
  void configure_contexts(std::function<void(BackendContext<B>&)> fn) {
    configure_ = std::move(fn);
    configure_(ctx_);
    if (world_) configure_(world_->context());
  }

  void load_dcae(const ModelFiles& f, const Console& con) override { dcae_.emplace(app::load_dcae<B, W>(f, con)); }
  void load_world(const ModelFiles& f, const Console& con) override {
    world_.emplace(app::load_world<B, W>(f, compute_, con, shard_));
    if (configure_) configure_(world_->context());
  }
  void release_dcae() override { dcae_.reset(); }
  const DcaeConfig& dcae_config() const override { return dcae().config(); }

  Tensor<float> encode(const io::Image& frame) override {
    return to_host(dcae().encode(ctx_, BackendTraits<B>::upload(io::image_to_tensor(frame))));
  }
  Tensor<float> decode(const Tensor<float>& latents, bool is_video) override {
    return to_host(dcae().decode(ctx_, BackendTraits<B>::upload(latents), is_video));
  }
  bool decodes_beside_steps() const override { return !is_host_backend<B>; }
  Tensor<float> plan(const History& window, const SampleOptions& opt) override { return world().plan(window, opt); }
  Tensor<float> plan_hypotheses(const History& window, std::int64_t K, const SampleOptions& opt) override {
    return world().plan_hypotheses(window, K, opt);
  }
  using Engine::step;
  StepResult step(const History& window, const NextAction* action, const DitSamplers& samplers,
                  NoiseSource& noise) override {
    return world().run_step(window, action, true, samplers, noise, {});
  }

 private:
  static BackendContext<B> make_context(const ComputeOptions& c) {
    if constexpr (std::is_same_v<B, Cpu>)
      return BackendContext<B>(c.threads);
    else
      return BackendContext<B>();
  }
  Tensor<float> to_host(const Tensor<float, B>& t) {
    if constexpr (is_host_backend<B>) {
      return t;
    } else {
      Tensor<float> host(t.shape());
      BackendTraits<B>::download_into(ctx_, t, host);
      return host;
    }
  }
  Dcae<B, W>& dcae() {
    EPONA_CHECK(dcae_.has_value(), "internal: the DC-AE is not loaded");
    return *dcae_;
  }
  const Dcae<B, W>& dcae() const {
    EPONA_CHECK(dcae_.has_value(), "internal: the DC-AE is not loaded");
    return *dcae_;
  }
  WorldModel<B, W>& world() {
    EPONA_CHECK(world_.has_value(), "internal: the world model is not loaded");
    return *world_;
  }

  struct AtDestruction {
    std::function<void()> fn;
    ~AtDestruction() {
      if (fn) fn();
    }
  };
  AtDestruction after_destruction_;  // first member: destroyed after all the others
  ComputeOptions compute_;
  VisShard shard_;
  std::function<void(BackendContext<B>&)> configure_;
  BackendContext<B> ctx_;  // the DC-AE's (the world model owns its own)
  std::optional<Dcae<B, W>> dcae_;
  std::optional<WorldModel<B, W>> world_;
};

}  // namespace epona::app
