// The "bench-mid" world model of pytorch-baseline.md (image 256x512 -> 8x16 latents, 10
// frames, MST 1024/8 heads/4 blocks, VisDiT 1024/8 heads 2+2, TrajDiT 512/4 heads 1+1) with
// random weights and inputs, shared by the CPU benchmarks (world_cpu.cpp: Google Benchmark;
// cpu_bench_mid.cpp: the side-by-side with PyTorch), so both time the same model on the same data.
#pragma once

#include <cstdint>
#include <utility>

#include "epona/core/arena.hpp"
#include "epona/model/pose_tokenizer.hpp"
#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"

namespace epona::bench {

inline WorldModelConfig bench_mid() {
  WorldModelConfig c;
  c.image_h = 256;
  c.image_w = 512;
  c.condition_frames = 10;
  c.n_embd = 1024;
  c.n_head = 8;
  c.n_layer = {4, 2, 2};
  c.n_embd_dit = 1024;
  c.n_head_dit = 8;
  c.axes_dim_dit = {16, 56, 56};
  c.n_layer_traj = {1, 1};
  c.n_embd_dit_traj = 512;
  c.n_head_dit_traj = 4;
  c.axes_dim_dit_traj = {16, 56, 56};
  c.traj_len = 15;
  return c;
}

// Standard normal values (torch's generator, `seed`) times `scale`.
inline Tensor<float, Cpu> randn(Shape shape, std::uint64_t seed, float scale = 1.0f) {
  TorchGenerator gen(seed);
  auto t = gen.randn(std::move(shape));
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] *= scale;
  return t;
}

// The model, its MST inputs and the MST outputs the DiTs condition on (after evaluate_mst).
template <class W>
struct BenchMidWorld {
  WorldModelConfig cfg = bench_mid();
  WorldModel<Cpu, W> wm = WorldModel<Cpu, W>::load(model::random_world_weights(cfg, 7), cfg);
  Tensor<float, Cpu> latents = randn({1, cfg.condition_frames, cfg.img_tokens(), cfg.token_dim()}, 1);
  Tensor<float, Cpu> pose_idx =
      model::PoseTokenizer::from(cfg).poses_to_indices(randn({1, cfg.condition_frames + 1, 2}, 2, 0.5f));
  Tensor<float, Cpu> yaw_idx =
      model::PoseTokenizer::from(cfg).yaws_to_indices(randn({1, cfg.condition_frames + 1, 1}, 3));
  Tensor<float, Cpu> stt{1, cfg.tokens_per_frame(), cfg.n_embd}, pose_emb{1, cfg.pose_emb_dim()};
  model::DitIds ids = model::prepare_ids(1, cfg.latent_h(), cfg.latent_w(), cfg.tokens_per_frame(), cfg.traj_len);
  Arena<Cpu> mst_arena{wm.mst().evaluate_workspace_bytes()};

  void evaluate_mst() {
    mst_arena.reset();
    wm.mst().evaluate(wm.context(), mst_arena, latents, pose_idx, yaw_idx, stt, pose_emb);
  }
  // A DiT evaluation's input (4: the seed both benchmarks use) for the VisDiT or the TrajDiT.
  Tensor<float, Cpu> dit_input(bool vis) const {
    const auto& dit = vis ? wm.vis_dit() : wm.traj_dit();
    return randn({1, (vis ? ids.img : ids.traj).size(1), dit.config().in_channels}, 4);
  }
};

}  // namespace epona::bench
