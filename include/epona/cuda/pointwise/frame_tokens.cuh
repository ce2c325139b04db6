// epona/cuda/pointwise/frame_tokens.cuh — the MST's input tokens in one launch (FrameTokens in
// core/kernel_options.hpp): the image projector's LayerNorm over all frames' image rows, each
// row written into its frame's slot with the frame's time embedding added, and the action rows
// copied in with theirs. Composed from separate passes this is 5 launches per frame (50 for
// the 10-frame window, ~100 µs on the H200); here it is one pass over the rows.
#pragma once

#include <cstdint>

#include "epona/core/kernel_options.hpp"
#include "epona/cuda/pointwise/norm.cuh"

namespace epona::cuda {

using epona::FrameTokens;

namespace detail {

// Adds a float32 row (a frame's time embedding) to a pack of LN results before they are stored:
// the LN output is rounded to float32 first and the add rounds once more, as the separate add.
struct AddRowPack {
  const float* row;
  __device__ void operator()(float (&v)[kPack], int c) const {
    float t[kPack];
    load8(row + c, t);
#pragma unroll
    for (int i = 0; i < kPack; ++i) v[i] = __fadd_rn(v[i], t[i]);
  }
};

template <class TI>
struct FrameTokenArgs {
  RowNormArgs<TI, TI, TI, float, float> norm;  // the image rows (F·L of them) into the tokens
  const float* actions;
  const float* time_emb;
  FrameTokens t;
};

// A warp per row: the first items·F·L rows are image rows (LN, in the pass order), the
// items·F·A after them action rows (copy + add); item b's frame f is output frame f·items + b.
template <class TI, int P>
__global__ void __launch_bounds__(32 * kNormWarps) frame_tokens_kernel(FrameTokenArgs<TI> a) {
  wait_for_producer();  // may start before its producer ends (launch_after)
  const std::int64_t image_rows = a.norm.rows, item = blockIdx.x * std::int64_t{kNormWarps} + threadIdx.x / 32;
  const std::int64_t F = a.t.frames, items = a.t.items;
  if (item >= image_rows + items * F * a.t.actions) return;
  const int lane = threadIdx.x & 31;
  const std::int64_t C = a.t.width, T = a.t.tokens();
  if (item < image_rows) {
    const std::int64_t row = pass_index(item, image_rows, a.norm.reverse), bf = row / a.t.image_rows;
    const std::int64_t f = bf % F, frame = f * items + bf / F;
    norm_row<P, false, false>(a.norm, row, lane, 32, [](float v) { return warp_sum(v); },
                              AddRowPack{a.time_emb + f * C}, frame * T + a.t.actions + row % a.t.image_rows);
    return;
  }
  const std::int64_t bf = (item - image_rows) / a.t.actions, slot = (item - image_rows) % a.t.actions;
  const std::int64_t b = bf / F, f = bf % F;
  const float* src = a.actions + (slot * a.t.action_entries + b * a.t.item_entries() + f) * C;
  float* dst = a.norm.out + ((f * items + b) * T + slot) * C;
  for (std::int64_t c = lane * kPack; c < C; c += 32 * kPack) {
    float v[kPack];
    load8(src + c, v);
    AddRowPack{a.time_emb + f * C}(v, static_cast<int>(c));
    store8(dst + c, v);
  }
}

}  // namespace detail

// The MST's tokens (FrameTokens) from the image projector's pre-norm rows `image`
// (items·frames·image_rows, width), the action embeddings, time_emb (frames, width) and the
// LN's weight and bias (either may be null), into out (frames·items, tokens, width). One launch when the
// width is a multiple of 8 of at most kWarpRowMax and every pointer is 16-byte aligned;
// otherwise it returns false and writes nothing (the caller composes the separate passes).
template <class TI>
bool try_assemble_frame_tokens(Context& ctx, const TI* image, const float* actions, const float* time_emb,
                               const float* weight, const float* bias, float* out, const FrameTokens& t) {
  static_assert(is_device_float<TI>, "frame tokens take float or bf16 image rows");
  EPONA_CHECK(t.frames >= 0 && t.image_rows >= 0 && t.actions >= 0 && t.width > 0 && t.items >= 1,
              "assemble_frame_tokens: bad extent (frames ", t.frames, ", image rows ", t.image_rows, ", actions ",
              t.actions, ", width ", t.width, ", items ", t.items, ")");
  EPONA_CHECK(t.actions == 0 || (t.action_entries % t.items == 0 && t.item_entries() >= t.frames),
              "assemble_frame_tokens: ", t.action_entries, " action entries for ", t.items, " item(s) of ", t.frames,
              " frames");
  const std::int64_t rows = t.items * t.frames * t.image_rows, items = rows + t.items * t.frames * t.actions;
  EPONA_CHECK(items <= 0x7fffffffLL * detail::kNormWarps, "assemble_frame_tokens: ", items, " rows exceed one launch");
  if (items == 0) return true;
  EPONA_CHECK(out != nullptr && time_emb != nullptr && (rows == 0 || image != nullptr) &&
                  (t.actions == 0 || actions != nullptr),
              "assemble_frame_tokens: null input or output");
  const std::int64_t n = t.width;
  using detail::packable;
  if (n > detail::kWarpRowMax || !packable(image, n, n) || !packable(actions, n, n) || !packable(time_emb, n, n) ||
      !packable(weight, n, 0) || !packable(bias, n, 0) || !packable(out, n, n))
    return false;
  const detail::FrameTokenArgs<TI> args{{image, nullptr, nullptr, nullptr, out, weight, bias, rows, n, t.eps,
                                         ctx.policy().reversed_passes},
                                        actions, time_emb, t};
  const auto blocks = static_cast<unsigned>((items + detail::kNormWarps - 1) / detail::kNormWarps);
  detail::with_warp_row_packs(n, [&](auto packs) {
    detail::launch_after(detail::frame_tokens_kernel<TI, decltype(packs)::value>, blocks, 32 * detail::kNormWarps, 0,
                         ctx, args);
  });
  EPONA_CUDA_CHECK_LAUNCH();
  return true;
}

}  // namespace epona::cuda
