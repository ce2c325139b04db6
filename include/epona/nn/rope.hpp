// epona/nn/rope.hpp — rotary-embedding tables (cos, sin per token and complex pair) and their
// application to packed q/k buffers. Two builders: the MST's 2-D axial table
// (utils/rope_2d.py `compute_axial_cis`, fp32) and the DiTs' 3-axis table (FLUX `EmbedND`,
// float64 angles rounded to fp32). Tables are built on the host once per configuration.
#pragma once

#include <cmath>
#include <cstdint>
#include <numeric>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona::nn {

// cos/sin of the rotation angle of pair p (channels 2p, 2p+1) of token r, shape (rows, pairs).
template <class B = Cpu>
struct RopeTable {
  Tensor<float, B> cos, sin;
  std::int64_t rows() const { return cos.empty() ? 0 : cos.size(0); }
  std::int64_t pairs() const { return cos.empty() ? 0 : cos.size(1); }
};

template <class B>
RopeTable<B> upload(const RopeTable<Cpu>& host) {
  return {BackendTraits<B>::upload(host.cos), BackendTraits<B>::upload(host.sin)};
}

// MST: compute_axial_cis(dim=head_dim, end_x, end_y, theta). Token t gets x = t % end_x and
// y = t // end_x (the official modulus is end_x = latent height although tokens are row-major
// over (h, w): reproduced, not fixed). Pairs [0, d/4) rotate with x, [d/4, d/2) with y,
// frequency 1 / theta^((4j)/d); all in fp32 like the official table.
inline RopeTable<Cpu> axial_rope_table(std::int64_t head_dim, std::int64_t end_x, std::int64_t end_y, float theta) {
  EPONA_CHECK(head_dim > 0 && head_dim % 4 == 0, "axial RoPE: head dim ", head_dim, " is not a multiple of 4");
  EPONA_CHECK(end_x > 0 && end_y > 0, "axial RoPE: grid ", end_x, " x ", end_y);
  const std::int64_t quarter = head_dim / 4, rows = end_x * end_y;
  std::vector<float> freq(static_cast<std::size_t>(quarter));
  for (std::int64_t j = 0; j < quarter; ++j) {
    const float exponent = static_cast<float>(4 * j) / static_cast<float>(head_dim);
    freq[j] = 1.0f / std::pow(theta, exponent);
  }
  RopeTable<Cpu> t{Tensor<float, Cpu>({rows, 2 * quarter}), Tensor<float, Cpu>({rows, 2 * quarter})};
  for (std::int64_t r = 0; r < rows; ++r) {
    const float pos[2] = {static_cast<float>(r % end_x), static_cast<float>(r / end_x)};
    for (int axis = 0; axis < 2; ++axis)
      for (std::int64_t j = 0; j < quarter; ++j) {
        const float angle = pos[axis] * freq[j];
        t.cos.at(r, axis * quarter + j) = std::cos(angle);
        t.sin.at(r, axis * quarter + j) = std::sin(angle);
      }
  }
  return t;
}

// DiTs: EmbedND(dim, theta, axes_dim) on ids (rows, n_axes). Axis i owns axes_dim[i]/2 pairs,
// laid out axis after axis; omega = 1/theta^(2m/axes_dim[i]) and the angle id·omega in
// float64, cos/sin in float64, then rounded to fp32 (as the official `rope` + `.float()`).
inline RopeTable<Cpu> nd_rope_table(const Tensor<float, Cpu>& ids, const std::vector<std::int64_t>& axes_dim,
                                    double theta) {
  EPONA_CHECK(ids.dim() == 2 && ids.size(1) == static_cast<std::int64_t>(axes_dim.size()), "RoPE ids ",
              shape_str(ids.shape()), " do not have one column per axis (", axes_dim.size(), " axes)");
  std::int64_t pairs = 0;
  for (auto a : axes_dim) {
    EPONA_CHECK(a > 0 && a % 2 == 0, "RoPE axis width ", a, " is not positive and even");
    pairs += a / 2;
  }
  const std::int64_t rows = ids.size(0);
  RopeTable<Cpu> t{Tensor<float, Cpu>({rows, pairs}), Tensor<float, Cpu>({rows, pairs})};
  for (std::int64_t r = 0; r < rows; ++r) {
    std::int64_t p = 0;
    for (std::size_t axis = 0; axis < axes_dim.size(); ++axis) {
      const double pos = static_cast<double>(ids.at(r, static_cast<std::int64_t>(axis)));
      const std::int64_t dim = axes_dim[axis];
      for (std::int64_t m = 0; m < dim / 2; ++m, ++p) {
        const double omega = 1.0 / std::pow(theta, static_cast<double>(2 * m) / static_cast<double>(dim));
        const double angle = pos * omega;
        t.cos.at(r, p) = static_cast<float>(std::cos(angle));
        t.sin.at(r, p) = static_cast<float>(std::sin(angle));
      }
    }
  }
  return t;
}

// Rotates `rows` tokens of one packed buffer (q or k) with table rows [first_row, first_row + rows).
template <class Context, class B, class T>
void apply_rope_rows(Context& ctx, T* x, std::int64_t rows, std::int64_t stride, std::int64_t heads,
                     const RopeTable<B>& table, std::int64_t first_row = 0) {
  EPONA_CHECK(first_row >= 0 && first_row + rows <= table.rows(), "RoPE: rows [", first_row, ", ",
              first_row + rows, ") outside a table of ", table.rows());
  const std::int64_t pairs = table.pairs();
  apply_rope(ctx, x, rows, stride, heads, 2 * pairs, table.cos.data() + first_row * pairs,
             table.sin.data() + first_row * pairs);
}

// Rotates q and k of `rows` tokens in place with rows [first_row, first_row + rows) of the table.
// q of token r starts at q + r*stride; heads of head_dim = 2·pairs channels side by side.
template <class Context, class B, class T>
void apply_rope_qk(Context& ctx, T* q, T* k, std::int64_t rows, std::int64_t stride, std::int64_t heads,
                   const RopeTable<B>& table, std::int64_t first_row = 0) {
  apply_rope_rows(ctx, q, rows, stride, heads, table, first_row);
  apply_rope_rows(ctx, k, rows, stride, heads, table, first_row);
}

}  // namespace epona::nn
