// apps/epona/sharded_engine.hpp — `--tensor-parallel N`: the world model's VisDiT split over N
// shards (docs/parallel.md). One ModelEngine per shard, each made and run in a thread of the
// shards' group (GPU r with --backend cuda: cuda::PeerShardGroup or NcclShardGroup; threads on
// the CPU: cpu::ThreadShardGroup); every world-model call runs on all shards with the same inputs
// and draws, and shard 0's result is returned (they are the same). The DC-AE is shard 0's alone.
#pragma once

#include <algorithm>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <type_traits>
#include <vector>

#include "model_engine.hpp"

namespace epona::app {

template <class B, class W, class Group>
class ShardedEngine final : public Engine {
 public:
  using Model = ModelEngine<B, W>;

  // `sums` says how the group adds up the shards' parts (the program's note when it loads; empty:
  // none, as for the CPU's threads, which announce_compute names).
  ShardedEngine(const ComputeOptions& c, std::unique_ptr<Group> group, std::string sums)
      : group_(std::move(group)), engines_(static_cast<std::size_t>(group_->size())), sums_note_(std::move(sums)) {
    const std::int64_t n = group_->size();
    for (std::int64_t r = 0; r < n; ++r) sums_.push_back(group_->shard(r));
    ComputeOptions mine = c;
    if constexpr (std::is_same_v<B, Cpu>) {  // the CPU's cores shared between the shards
      const int all = c.threads > 0 ? c.threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
      mine.threads = threads_per_shard_ = std::max(1, all / static_cast<int>(n));
    }
    on_shards([&](std::int64_t r) {
      engines_[r] = std::make_unique<Model>(mine, typename WorldModel<B, W>::VisShard{{r, n}, &sums_[r]});
    });
  }

  // Each shard's engine is released in its thread (on its GPU).
  ~ShardedEngine() override {
    try {
      on_shards([&](std::int64_t r) { engines_[r].reset(); });
    } catch (...) {
      // A failing release leaves the rest to the members' destructors.
    }
  }

  // f(rank, engine) for each shard, in its thread (the CUDA engine sets its kernel policy here).
  template <class F>
  void each_shard(F&& f) {
    on_shards([&](std::int64_t r) { f(r, *engines_[r]); });
  }

  void load_dcae(const ModelFiles& f, const Console& con) override { first().load_dcae(f, con); }
  // Shard 0 says what it loads; the others load quietly.
  void load_world(const ModelFiles& f, const Console& con) override {
    if (!sums_note_.empty()) con.note("tensor parallel: the VisDiT over ", group_->size(), " shards, ", sums_note_);
    on_shards([&](std::int64_t r) {
      std::ostringstream sink;
      engines_[r]->load_world(f, r == 0 ? con : Console{sink, sink, true, false});
    });
  }
  void release_dcae() override { first().release_dcae(); }
  const DcaeConfig& dcae_config() const override { return engines_.front()->dcae_config(); }
  Tensor<float> encode(const io::Image& frame) override { return first().encode(frame); }
  Tensor<float> decode(const Tensor<float>& latents, bool is_video) override { return first().decode(latents, is_video); }
  bool decodes_beside_steps() const override { return engines_.front()->decodes_beside_steps(); }

  Tensor<float> plan(const History& window, const SampleOptions& opt) override {
    return on_every_shard([&](Model& e) { return e.plan(window, opt); });
  }
  Tensor<float> plan_hypotheses(const History& window, std::int64_t K, const SampleOptions& opt) override {
    return on_every_shard([&](Model& e) { return e.plan_hypotheses(window, K, opt); });
  }
  using Engine::step;
  // Every shard draws from a copy of `noise`; the caller's source then stands where shard 0's does.
  StepResult step(const History& window, const NextAction* action, const DitSamplers& samplers,
                  NoiseSource& noise) override {
    std::vector<NoiseSource> copies(engines_.size(), noise);
    std::vector<StepResult> results(engines_.size());
    on_shards([&](std::int64_t r) { results[r] = engines_[r]->step(window, action, samplers, copies[r]); });
    noise = copies.front();
    return results.front();
  }

 private:
  // f(rank) in every shard's thread (the group's: on its GPU); on the CPU with the thread's
  // OpenMP team sized to the shard's share of the cores (a context sets it for its thread).
  template <class F>
  void on_shards(F&& f) {
    group_->run([&](std::int64_t r) {
      if constexpr (std::is_same_v<B, Cpu>) (void)cpu::Context(threads_per_shard_);
      f(r);
    });
  }
  // Shard 0's engine: the main thread's device is GPU 0, as is the group's first (its DC-AE lives there).
  Model& first() { return *engines_.front(); }
  template <class F>
  auto on_every_shard(F&& f) {
    std::vector<decltype(f(*engines_.front()))> results(engines_.size());
    on_shards([&](std::int64_t r) { results[r] = f(*engines_[r]); });
    return results.front();
  }

  std::unique_ptr<Group> group_;  // first: the shards' engines go before their group
  std::vector<typename Group::Sum> sums_;
  std::vector<std::unique_ptr<Model>> engines_;
  int threads_per_shard_ = 1;
  std::string sums_note_;
};

}  // namespace epona::app
