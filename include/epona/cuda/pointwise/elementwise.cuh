// epona/cuda/pointwise/elementwise.cuh — residual and gating updates between the big GEMMs on the GPU:
// x += y, x += gate ⊙ y (gate broadcast over rows: adaLN's gated residual) and a row broadcast
// add. Mixed storage types round like PyTorch's promotion (bf16 ⊙ bf16 rounds to bf16 first).
#pragma once

#include <cstdint>

#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

namespace epona::cuda {

namespace detail {

// x[r, c] += gate[c] * y[r, c] on rows of width n; with y null, x[r, c] += gate[c] (the row
// broadcast add); with gate null, x[r, c] += y[r, c].
template <class TX, class TY, class TG>
struct AddEach {
  TX* x;
  const TY* y;
  const TG* gate;
  std::int64_t n;
  __device__ float update(float g, float v) const {
    if (!gate) return v;
    return y ? round_to<promote_t<TG, TY>>(g * v) : g;
  }
  __device__ void pack(std::int64_t r, std::int64_t c) const {
    float xs[kPack], ys[kPack] = {}, gs[kPack] = {};
    load8(x + r * n + c, xs);
    if (y) load8(y + r * n + c, ys);
    if (gate) load8(gate + c, gs);
#pragma unroll
    for (int i = 0; i < kPack; ++i) xs[i] += update(gs[i], ys[i]);
    store8(x + r * n + c, xs);
  }
  __device__ void one(std::int64_t r, std::int64_t c) const {
    const float g = gate ? to_f32(gate[c]) : 0.f, v = y ? to_f32(y[r * n + c]) : 0.f;
    x[r * n + c] = from_f32<TX>(to_f32(x[r * n + c]) + update(g, v));
  }
};

template <class TX, class TY, class TG>
void add_rows(Context& ctx, TX* x, const TY* y, const TG* gate, std::int64_t rows, std::int64_t n, const char* what) {
  static_assert(is_device_float<TX> && is_device_float<TY> && is_device_float<TG>, "residual ops take float or bf16");
  EPONA_CHECK(rows >= 0 && n >= 0, what, ": negative extent (rows ", rows, ", width ", n, ")");
  const bool packed = packable(x, n, n) && packable(y, n, n) && packable(gate, n, 0);
  for_each(ctx, rows, n, packed, AddEach<TX, TY, TG>{x, y, gate, n});
}

}  // namespace detail

// x[i] += y[i] for i < n.
template <class TX, class TY>
void add_inplace(Context& ctx, TX* x, const TY* y, std::int64_t n) {
  EPONA_CHECK(x != nullptr && y != nullptr, "add_inplace: null input");
  detail::add_rows(ctx, x, y, static_cast<const TX*>(nullptr), 1, n, "add_inplace");
}

// x[r, :] += gate[:] * y[r, :] for rows of width n.
template <class TX, class TY, class TG>
void add_gated(Context& ctx, TX* x, const TY* y, const TG* gate, std::int64_t rows, std::int64_t n) {
  EPONA_CHECK(x != nullptr && y != nullptr && gate != nullptr, "add_gated: null input");
  detail::add_rows(ctx, x, y, gate, rows, n, "add_gated");
}

// x[r, :] += b[:] for rows of width n.
template <class TX, class TB>
void add_row_broadcast(Context& ctx, TX* x, const TB* b, std::int64_t rows, std::int64_t n) {
  EPONA_CHECK(x != nullptr && b != nullptr, "add_row_broadcast: null bias");
  detail::add_rows(ctx, x, static_cast<const TX*>(nullptr), b, rows, n, "add_row_broadcast");
}

}  // namespace epona::cuda
