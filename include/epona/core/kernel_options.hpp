// epona/core/kernel_options.hpp — the options every backend's kernels take, defined once so that
// backend-generic layer code names one type: the GEMM epilogue, the attention mask and the
// strided attention shape. epona::cpu and epona::cuda re-export them.
#pragma once

#include <cstdint>

#include "epona/core/dtype.hpp"  // EPONA_HOST_DEVICE

namespace epona {

// What a GEMM applies to x · Wᵀ + b before storing it.
enum class Epilogue { None, GeluErf, GeluTanh, Silu };

enum class Mask { None, Causal };

// Element (s, i, h, d) of q lives at q[s * q_seq + i * q_row + h * head_dim + d]; same for k,
// v and o. Causal: query i sees keys j <= i (queries and keys aligned at the start).
// additive_mask: optional (lq, lk) float32, row-major, in the backend's memory, added to the
// scaled scores (0 / −inf masks, or biases).
struct AttentionShape {
  std::int64_t seqs = 1, heads = 1, lq = 0, lk = 0, head_dim = 0;
  std::int64_t q_seq = 0, q_row = 0, k_seq = 0, k_row = 0, v_seq = 0, v_row = 0, o_seq = 0, o_row = 0;
  float scale = 0;  // 0: 1/sqrt(head_dim)
  Mask mask = Mask::None;
  const float* additive_mask = nullptr;
};

// The same rows of several batch items for one row pass (a DiT's folded batch): item b's
// `rows` rows start at row b·stride of the output (and of the residual it updates), at row
// b·x_stride of a separate input, and its per-column vectors (shift, scale, gate) at +b·mod_stride
// elements. Pointers passed with it are item 0's first row and vectors.
struct NormItems {
  std::int64_t count = 1, rows = 0, stride = 0, x_stride = 0, mod_stride = 0;
};

// Several batch items of one packed [q | k | v] layout for one QK-norm + RoPE launch: item b's
// rows start `stride` rows after item b - 1's, and its RoPE table rows `rope_stride` rows after
// (0: one table for all); the segments name item 0's rows.
struct QkItems {
  std::int64_t count = 1, stride = 0, rope_stride = 0;
};

// The MST's input tokens of `frames` frames, (frames, actions + image_rows, width) float32:
// frame f's row slot < actions is action entry f of that slot plus time_emb[f]; its row
// actions + l is LN(image[f·image_rows + l]) · weight + bias + time_emb[f]. Action slot s,
// entry e lives at actions + (s·action_entries + e)·width.
// `items` windows fold frame-major (the MST's batch): item b's frame f is output frame
// f·items + b, read from image rows (b·frames + f)·image_rows on and action entry
// b·(action_entries / items) + f; items 1 is the layout above.
struct FrameTokens {
  std::int64_t frames = 0, image_rows = 0, actions = 0, action_entries = 0, width = 0;
  float eps = 1e-5f;
  std::int64_t items = 1;
  EPONA_HOST_DEVICE std::int64_t tokens() const { return actions + image_rows; }
  // Each item's action entries (the kernel reads them too).
  EPONA_HOST_DEVICE std::int64_t item_entries() const { return action_entries / items; }
};

}  // namespace epona
