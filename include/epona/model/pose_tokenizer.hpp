// epona/model/pose_tokenizer.hpp — the action side of the world model on the host:
// continuous pose/yaw "indices" (models/modules/tokenizer.py `poses_to_indices`,
// `yaws_to_indices`: scaled and clipped, never rounded), trajectory (de)normalisation
// (`normalize_traj` / `denormalize_traj`) and the DiT position ids (`prepare_ids`).
#pragma once

#include <algorithm>
#include <cstdint>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/model/config.hpp"

namespace epona::model {

struct PoseTokenizer {
  std::int64_t x_vocab = 128, y_vocab = 128, yaw_vocab = 512;
  double x_range = constants::tokenizer_x_range_m;
  double y_range = constants::tokenizer_y_range_m;
  double yaw_range = constants::tokenizer_yaw_range_deg;

  static PoseTokenizer from(const WorldModelConfig& c) {
    PoseTokenizer t;
    t.x_vocab = c.pose_x_vocab_size;
    t.y_vocab = c.pose_y_vocab_size;
    t.yaw_vocab = c.yaw_vocab_size;
    return t;
  }

  // clip(((v - min)·vocab)/range, 0, vocab) in fp32, in the official order (the Python
  // scalars min, vocab and range enter the fp32 tensor ops rounded to fp32).
  static float index(float v, double min, std::int64_t vocab, double range) {
    const float shifted = v - static_cast<float>(min);
    const float scaled = (shifted * static_cast<float>(vocab)) / static_cast<float>(range);
    return std::clamp(scaled, 0.0f, static_cast<float>(vocab));
  }
  // The bin centre offset: the lowest index sits half a bin above -range/2.
  static double centred_min(double range, std::int64_t vocab) { return -range / 2 + (range / double(vocab)) / 2; }

  float x_index(float x) const { return index(x, 0.0, x_vocab, x_range); }
  float y_index(float y) const { return index(y, centred_min(y_range, y_vocab), y_vocab, y_range); }
  float yaw_index(float yaw) const { return index(yaw, centred_min(yaw_range, yaw_vocab), yaw_vocab, yaw_range); }

  // poses (..., 2) [x, y] metres -> (..., 2) [x_idx, y_idx].
  Tensor<float, Cpu> poses_to_indices(const Tensor<float, Cpu>& poses) const {
    EPONA_CHECK(poses.dim() >= 1 && poses.size(-1) == 2, "poses_to_indices: expected (..., 2), got ",
                shape_str(poses.shape()));
    Tensor<float, Cpu> out(poses.shape());
    for (std::int64_t i = 0; i < poses.numel() / 2; ++i) {
      out.data()[2 * i] = x_index(poses.data()[2 * i]);
      out.data()[2 * i + 1] = y_index(poses.data()[2 * i + 1]);
    }
    return out;
  }
  // yaws (..., 1) degrees -> (..., 1) yaw_idx.
  Tensor<float, Cpu> yaws_to_indices(const Tensor<float, Cpu>& yaws) const {
    EPONA_CHECK(yaws.dim() >= 1 && yaws.size(-1) == 1, "yaws_to_indices: expected (..., 1), got ",
                shape_str(yaws.shape()));
    Tensor<float, Cpu> out(yaws.shape());
    for (std::int64_t i = 0; i < yaws.numel(); ++i) out.data()[i] = yaw_index(yaws.data()[i]);
    return out;
  }
};

// Normalised trajectory rows [x_n, y_n, yaw_n] <-> metres/degrees (last dim 3). Nothing is clipped.
struct TrajectoryScale {
  double x_bound = 50, y_bound = 10, yaw_bound = 12;

  static TrajectoryScale from(const WorldModelConfig& c) { return {c.pose_x_bound, c.pose_y_bound, c.yaw_bound}; }

  // denormalize_traj: x = ((x_n + 1)·x_bound)/2, y = y_n·y_bound, yaw = yaw_n·yaw_bound (fp32).
  void denormalize(Tensor<float, Cpu>& traj) const {
    check(traj);
    float* p = traj.data();
    for (std::int64_t i = 0; i < traj.numel() / 3; ++i) {
      p[3 * i] = ((p[3 * i] + 1.0f) * static_cast<float>(x_bound)) / 2.0f;
      p[3 * i + 1] = p[3 * i + 1] * static_cast<float>(y_bound);
      p[3 * i + 2] = p[3 * i + 2] * static_cast<float>(yaw_bound);
    }
  }
  // normalize_traj: x_n = (2·x)/x_bound - 1, y_n = y/y_bound, yaw_n = yaw/yaw_bound.
  void normalize(Tensor<float, Cpu>& traj) const {
    check(traj);
    float* p = traj.data();
    for (std::int64_t i = 0; i < traj.numel() / 3; ++i) {
      p[3 * i] = (2.0f * p[3 * i]) / static_cast<float>(x_bound) - 1.0f;
      p[3 * i + 1] = p[3 * i + 1] / static_cast<float>(y_bound);
      p[3 * i + 2] = p[3 * i + 2] / static_cast<float>(yaw_bound);
    }
  }

 private:
  static void check(const Tensor<float, Cpu>& traj) {
    EPONA_CHECK(traj.dim() >= 1 && traj.size(-1) == 3, "trajectory must end in [x, y, yaw], got ",
                shape_str(traj.shape()));
  }
};

// prepare_ids: image ids (batch, h·w, 3) = [0, row, col]; condition ids (batch, cond_len, 3)
// = 0; trajectory ids (batch, traj_len, 3) = [0, 0, k].
struct DitIds {
  Tensor<float, Cpu> img, cond, traj;
};

inline DitIds prepare_ids(std::int64_t batch, std::int64_t h, std::int64_t w, std::int64_t cond_len,
                          std::int64_t traj_len) {
  DitIds ids{Tensor<float, Cpu>::zeros({batch, h * w, 3}), Tensor<float, Cpu>::zeros({batch, cond_len, 3}),
             Tensor<float, Cpu>::zeros({batch, traj_len, 3})};
  for (std::int64_t b = 0; b < batch; ++b) {
    for (std::int64_t n = 0; n < h * w; ++n) {
      ids.img.at(b, n, 1) = static_cast<float>(n / w);
      ids.img.at(b, n, 2) = static_cast<float>(n % w);
    }
    for (std::int64_t k = 0; k < traj_len; ++k) ids.traj.at(b, k, 2) = static_cast<float>(k);
  }
  return ids;
}

}  // namespace epona::model
