// epona/cpu/attention.hpp — scaled-dot-product attention over strided, token-major data:
// softmax(q kᵀ · scale + mask) v per sequence and head, never materialising more than one
// row of scores. Strides let callers attend straight out of packed QKV buffers and across
// frames (the MST's temporal attention) without transposes.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "epona/cpu/context.hpp"

namespace epona::cpu {

enum class Mask { None, Causal };

// Element (s, i, h, d) of q lives at q[s * q_seq + i * q_row + h * head_dim + d]; same for k,
// v and o. Causal: query i sees keys j <= i (queries and keys aligned at the start).
struct AttentionShape {
  std::int64_t seqs = 1, heads = 1, lq = 0, lk = 0, head_dim = 0;
  std::int64_t q_seq = 0, q_row = 0, k_seq = 0, k_row = 0, v_seq = 0, v_row = 0, o_seq = 0, o_row = 0;
  float scale = 0;            // 0: 1/sqrt(head_dim)
  Mask mask = Mask::None;
  const float* additive_mask = nullptr;  // optional (lq, lk), added to the scores
};

inline void attention(Context&, const float* q, const float* k, const float* v, float* o,
                      const AttentionShape& a) {
  const float scale = a.scale != 0 ? a.scale : 1.0f / std::sqrt(static_cast<float>(a.head_dim));
  const std::int64_t D = a.head_dim;
#pragma omp parallel
  {
    std::vector<float> score(static_cast<std::size_t>(a.lk));
    std::vector<float> acc(static_cast<std::size_t>(D));
#pragma omp for collapse(2)
    for (std::int64_t s = 0; s < a.seqs; ++s)
      for (std::int64_t h = 0; h < a.heads; ++h)
        for (std::int64_t i = 0; i < a.lq; ++i) {
          const float* qi = q + s * a.q_seq + i * a.q_row + h * D;
          const std::int64_t nk = a.mask == Mask::Causal ? std::min(a.lk, i + 1) : a.lk;
          float mx = -std::numeric_limits<float>::infinity();
          for (std::int64_t j = 0; j < nk; ++j) {
            const float* kj = k + s * a.k_seq + j * a.k_row + h * D;
            float dot = 0;
            for (std::int64_t d = 0; d < D; ++d) dot += qi[d] * kj[d];
            float sc = dot * scale;
            if (a.additive_mask) sc += a.additive_mask[i * a.lk + j];
            score[j] = sc;
            mx = std::max(mx, sc);
          }
          float denom = 0;
          for (std::int64_t j = 0; j < nk; ++j) {
            score[j] = mx == -std::numeric_limits<float>::infinity() ? 0.f : std::exp(score[j] - mx);
            denom += score[j];
          }
          std::fill(acc.begin(), acc.end(), 0.f);
          for (std::int64_t j = 0; j < nk; ++j) {
            const float* vj = v + s * a.v_seq + j * a.v_row + h * D;
            const float p = score[j];
            for (std::int64_t d = 0; d < D; ++d) acc[d] += p * vj[d];
          }
          float* oi = o + s * a.o_seq + i * a.o_row + h * D;
          const float inv = denom > 0 ? 1.0f / denom : 0.f;
          for (std::int64_t d = 0; d < D; ++d) oi[d] = acc[d] * inv;
        }
  }
}

}  // namespace epona::cpu
