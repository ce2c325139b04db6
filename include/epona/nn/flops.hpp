// epona/nn/flops.hpp — FLOP counts as the roofline figures of docs/performance.md take them:
// 2·M·N·K per Linear (bias adds ignored), 4·H·Lq·Lk·d per attention call; norms, activations,
// RoPE and residual adds excluded. Kept apart so GEMM-only figures (docs/performance.md quotes
// both) can be quoted next to the totals.
#pragma once

namespace epona::nn {

struct Flops {
  double gemm = 0, attention = 0;
  double total() const { return gemm + attention; }
  Flops& operator+=(const Flops& o) {
    gemm += o.gemm;
    attention += o.attention;
    return *this;
  }
  friend Flops operator+(Flops a, const Flops& b) { return a += b; }
  friend Flops operator*(double k, Flops a) {
    a.gemm *= k;
    a.attention *= k;
    return a;
  }
};

}  // namespace epona::nn
