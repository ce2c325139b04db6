// epona/model/random_weights.hpp — a world-model weight map with random values under every
// official key (docs/checkpoints.md: `module.model.`, `module.dit.`, `module.traj_dit.`),
// sized from a WorldModelConfig: for benchmarks and examples at any size without a
// checkpoint. Linear weights ~ U(±1/sqrt(fan_in)) so activations stay O(1); norms near 1/0.
#pragma once

#include <cmath>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/model/config.hpp"

namespace epona::model {

namespace detail {
class WeightSynth {
 public:
  explicit WeightSynth(std::uint64_t seed) : state_(seed * 0x9E3779B97F4A7C15ull + 1), map_("random world weights") {}

  void add(const std::string& name, const Shape& shape, float scale, float offset = 0) {
    auto data = std::make_shared<std::vector<float>>(static_cast<std::size_t>(shape_numel(shape)));
    for (auto& v : *data) v = offset + scale * uniform();
    io::RawTensor r;
    r.dtype = DType::F32;
    r.shape = shape;
    r.bytes = std::span<const std::byte>(reinterpret_cast<const std::byte*>(data->data()), data->size() * sizeof(float));
    map_.keep_alive(data);
    map_.add(name, r);
  }
  void linear(const std::string& p, std::int64_t in, std::int64_t out, bool bias) {
    add(p + "weight", {out, in}, 1.0f / std::sqrt(float(in)));
    if (bias) add(p + "bias", {out}, 0.05f);
  }
  void layer_norm(const std::string& p, std::int64_t n) {
    add(p + "weight", {n}, 0.1f, 1.0f);
    add(p + "bias", {n}, 0.1f);
  }
  io::TensorMap take() { return std::move(map_); }

 private:
  // xorshift64*: fast, and good enough for random weights (uniform in [-1, 1)).
  float uniform() {
    state_ ^= state_ >> 12;
    state_ ^= state_ << 25;
    state_ ^= state_ >> 27;
    const std::uint64_t r = state_ * 0x2545F4914F6CDD1Dull;
    return static_cast<float>(r >> 40) * 0x1p-23f - 1.0f;
  }
  std::uint64_t state_;
  io::TensorMap map_;
};

inline void synth_mst(WeightSynth& w, const WorldModelConfig& c) {
  const std::string p = "module.model.";
  const std::int64_t C = c.n_embd;
  w.add(p + "time_emb", {constants::mst_time_emb_rows, C}, 0.5f);
  w.linear(p + "img_projector.0.", c.token_dim(), c.mst_img_projector_hidden(), false);
  w.linear(p + "img_projector.2.", c.mst_img_projector_hidden(), C, false);
  w.layer_norm(p + "img_projector.3.", C);
  for (const char* s : {"pose_x", "pose_y", "yaw"}) {
    const std::string q = p + s + "_projector.";
    w.linear(q + "0.", constants::fourier_embed_dim, constants::pose_projector_hidden, false);
    w.linear(q + "2.", constants::pose_projector_hidden, C, false);
    w.layer_norm(q + "3.", C);
  }
  for (std::int64_t i = 0; i < c.mst_depth(); ++i)
    for (const char* s : {"causal_time_block", "space_block"}) {
      const std::string q = p + "causal_time_space_blocks." + std::to_string(i) + "." + s + ".";
      w.layer_norm(q + "ln1.", C);
      w.layer_norm(q + "ln2.", C);
      for (const char* l : {"query", "key", "value", "proj"}) w.linear(q + "attn." + l + ".", C, C, false);
      w.layer_norm(q + "attn.q_norm.", C);
      w.layer_norm(q + "attn.k_norm.", C);
      w.linear(q + "mlp.0.", C, 4 * C, false);
      w.linear(q + "mlp.2.", 4 * C, C, false);
    }
}

inline void synth_dit(WeightSynth& w, const std::string& p, const std::string& input, std::int64_t io_channels,
                      std::int64_t D, std::int64_t heads, std::int64_t vec_in, std::int64_t n_double,
                      std::int64_t n_single, std::int64_t context) {
  const std::int64_t Dm = constants::dit_mlp_ratio * D, d = D / heads;
  w.linear(p + input + ".", io_channels, D, true);
  w.linear(p + "time_in.in_layer.", constants::timestep_embed_dim, D, true);
  w.linear(p + "time_in.out_layer.", D, D, true);
  if (vec_in > 0) {
    w.linear(p + "vector_in.in_layer.", vec_in, D, true);
    w.linear(p + "vector_in.out_layer.", D, D, true);
  }
  w.linear(p + "cond_in.", context, D, true);
  for (std::int64_t i = 0; i < n_double; ++i)
    for (const char* s : {"img", "cond"}) {
      const std::string q = p + "double_blocks." + std::to_string(i) + "." + s;
      w.linear(q + "_mod.lin.", D, 6 * D, true);
      w.linear(q + "_attn.qkv.", D, 3 * D, true);
      w.add(q + "_attn.norm.query_norm.scale", {d}, 0.1f, 1.0f);
      w.add(q + "_attn.norm.key_norm.scale", {d}, 0.1f, 1.0f);
      w.linear(q + "_attn.proj.", D, D, true);
      w.linear(q + "_mlp.0.", D, Dm, true);
      w.linear(q + "_mlp.2.", Dm, D, true);
    }
  for (std::int64_t j = 0; j < n_single; ++j) {
    const std::string q = p + "single_blocks." + std::to_string(j) + ".";
    w.linear(q + "linear1.", D, 3 * D + Dm, true);
    w.linear(q + "linear2.", D + Dm, D, true);
    w.add(q + "norm.query_norm.scale", {d}, 0.1f, 1.0f);
    w.add(q + "norm.key_norm.scale", {d}, 0.1f, 1.0f);
    w.linear(q + "modulation.lin.", D, 3 * D, true);
  }
  w.linear(p + "final_layer.linear.", D, io_channels, true);
  w.linear(p + "final_layer.adaLN_modulation.1.", D, 2 * D, true);
}
}  // namespace detail

inline io::TensorMap random_world_weights(const WorldModelConfig& c, std::uint64_t seed = 1) {
  c.validate();
  detail::WeightSynth w(seed);
  detail::synth_mst(w, c);
  detail::synth_dit(w, "module.dit.", "img_in", c.token_dim(), c.n_embd_dit, c.n_head_dit, c.vis_vec_in_dim(),
                    c.vis_double_blocks(), c.vis_single_blocks(), c.context_in_dim());
  detail::synth_dit(w, "module.traj_dit.", "traj_in", constants::traj_token_size, c.n_embd_dit_traj,
                    c.n_head_dit_traj, 0, c.traj_double_blocks(), c.traj_single_blocks(), c.context_in_dim());
  return w.take();
}

}  // namespace epona::model
