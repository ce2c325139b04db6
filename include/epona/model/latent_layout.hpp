// epona/model/latent_layout.hpp — the two layouts of a DC-AE latent: the world model's tokens
// (N, L, C) / (B, T, L, C) / (N, h, w, C), row-major over (h, w) with channels last (token
// l = y·w + x, the tokenizer's patchify with patch 1), and the DC-AE's NCHW (N, C, h, w).
#pragma once

#include <cstdint>

#include "epona/core/tensor.hpp"
#include "epona/cpu/pixel_shuffle.hpp"

namespace epona {

// tokens (N, L, C), (B, T, L, C) or (N, h, w, C) with L = h·w  ->  latent (N·…, C, h, w).
template <class Ctx, class B>
Tensor<float, B> tokens_to_latent(Ctx& ctx, const Tensor<float, B>& tokens, std::int64_t h, std::int64_t w) {
  EPONA_CHECK(h > 0 && w > 0, "tokens_to_latent: latent grid ", h, "x", w, " must be positive");
  const bool grid = tokens.dim() == 4 && tokens.size(1) == h && tokens.size(2) == w;
  EPONA_CHECK(tokens.dim() >= 3 && (grid || tokens.size(-2) == h * w), "tokens_to_latent: expected (N, ", h * w,
              ", C), (B, T, ", h * w, ", C) or (N, ", h, ", ", w, ", C) tokens, got ", shape_str(tokens.shape()));
  const std::int64_t C = tokens.size(-1), L = h * w, N = tokens.numel() / (L * C);
  Tensor<float, B> latent({N, C, h, w});
  transpose_last2(ctx, tokens.data(), latent.data(), N, L, C);
  return latent;
}

// latent (N, C, h, w)  ->  tokens (N, L, C); reshape to (B, T, L, C) as needed.
template <class Ctx, class B>
Tensor<float, B> latent_to_tokens(Ctx& ctx, const Tensor<float, B>& latent) {
  EPONA_CHECK(latent.dim() == 4, "latent_to_tokens: expected an (N, C, h, w) latent, got ",
              shape_str(latent.shape()));
  const std::int64_t N = latent.size(0), C = latent.size(1), L = latent.size(2) * latent.size(3);
  Tensor<float, B> tokens({N, L, C});
  transpose_last2(ctx, latent.data(), tokens.data(), N, C, L);
  return tokens;
}

}  // namespace epona
