// epona/cpu/conv_winograd.hpp — 3x3 stride-1 "same" convolutions (the DC-AE's ResBlock and
// resampling convs) by Winograd's minimal filtering F(2x2, 3x3): 16 multiply-adds per input
// channel and 2x2 output tile instead of 36 (2.25x fewer), as 16 GEMMs on the packed micro-kernels
// between a transform of the input tiles and one of the products, bias and ReLU/SiLU fused into
// the output transform. Mirrors torch.nn.Conv2d(k=3, padding=1) up to float32 rounding.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <string_view>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/cpu/activation.hpp"
#include "epona/cpu/context.hpp"
#include "epona/cpu/gemm.hpp"

namespace epona::cpu::winograd {

// With the interpolation points (0, 1, -1, inf):
//   B^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1]   (input tile d, 4x4:  V = B^T d B)
//   G   = [1 0 0; 1/2 1/2 1/2; 1/2 -1/2 1/2; 0 0 1]  (kernel g, 3x3:     U = G g G^T)
//   A^T = [1 1 1 0; 0 1 -1 -1]                       (product m, 4x4:   Y = A^T m A, 2x2)
// The only constants are 1 and 1/2 (exact), so the transforms round only their additions: the
// result differs from the direct sum by a few float32 roundings more (tests/nn/dcae_conv.cpp).
inline constexpr std::int64_t kElems = 16;  // elements of a transformed tile, e = 4·i + j

// Tiles of 2x2 outputs covering an H x W map.
struct Tiling {
  std::int64_t rows = 0, cols = 0;  // tile rows ceil(H/2), tile columns ceil(W/2)
  std::int64_t count() const { return rows * cols; }
};
inline Tiling tiling(std::int64_t H, std::int64_t W) { return {(H + 1) / 2, (W + 1) / 2}; }

// U[e][o][c] = (G g G^T)[e] for the 3x3 kernel g of output o and input c; w is [cout][cin][3][3].
// Per output: its kernels transposed to [9][cin] first, so that the transform is vector
// arithmetic over c with contiguous loads and stores.
template <class W>
void transform_weights(const W* w, std::int64_t cout, std::int64_t cin, float* u) {
  const std::int64_t plane = cout * cin;
#pragma omp parallel if (plane >= 4096)
  {
    std::vector<float> taps(static_cast<std::size_t>(9 * cin));  // [row·3 + col][c]
#pragma omp for schedule(static)
    for (std::int64_t o = 0; o < cout; ++o) {
      for (std::int64_t c = 0; c < cin; ++c)
        for (int k = 0; k < 9; ++k) taps[static_cast<std::size_t>(k * cin + c)] = float(w[(o * cin + c) * 9 + k]);
      const float* g = taps.data();
      float* uo = u + o * cin;
      for (int i = 0; i < 4; ++i) {  // row i of G g: rows of g combined as G's row i says
        const auto gg = [&](int col, std::int64_t c) {
          const float g0 = g[(0 + col) * cin + c], g1 = g[(3 + col) * cin + c], g2 = g[(6 + col) * cin + c];
          return i == 0 ? g0 : i == 1 ? 0.5f * (g0 + g1 + g2) : i == 2 ? 0.5f * (g0 - g1 + g2) : g2;
        };
        float* u0 = uo + 4 * i * plane;
        float* u1 = u0 + plane;
        float* u2 = u1 + plane;
        float* u3 = u2 + plane;
#pragma omp simd
        for (std::int64_t c = 0; c < cin; ++c) {  // (G g) G^T, row i
          const float t0 = gg(0, c), t1 = gg(1, c), t2 = gg(2, c);
          u0[c] = t0;
          u1[c] = 0.5f * (t0 + t1 + t2);
          u2[c] = 0.5f * (t0 - t1 + t2);
          u3[c] = t2;
        }
      }
    }
  }
}

// V[e][c][t] = (B^T d B)[e] for every tile t = ty·cols + tx of every channel c, d the 4x4 input
// window at rows 2ty-1.., columns 2tx-1.. (zero outside the image). Along a tile row the
// windows' columns are the padded row's even and odd elements E, O (window t = E[t], O[t],
// E[t+1], O[t+1]), so both transform passes are contiguous vector arithmetic over t.
inline void transform_input(const float* in, std::int64_t cin, std::int64_t H, std::int64_t W, const Tiling& tl,
                            float* v) {
  const std::int64_t n = tl.cols, T = tl.count(), plane = cin * T;
#pragma omp parallel
  {
    std::vector<float> scratch(static_cast<std::size_t>(4 * 2 * (n + 1) + 16 * n));
#pragma omp for collapse(2) schedule(static)
    for (std::int64_t c = 0; c < cin; ++c)
      for (std::int64_t ty = 0; ty < tl.rows; ++ty) {
        float* even = scratch.data();                 // [4][n + 1]
        float* odd = even + 4 * (n + 1);              // [4][n + 1]
        float* h = odd + 4 * (n + 1);                 // [4 rows][4 j][n]
        for (std::int64_t r = 0; r < 4; ++r) {
          const std::int64_t y = 2 * ty - 1 + r;
          float* e = even + r * (n + 1);
          float* o = odd + r * (n + 1);
          if (y < 0 || y >= H) {
            std::fill_n(e, n + 1, 0.f);
            std::fill_n(o, n + 1, 0.f);
          } else {
            const float* row = in + (c * H + y) * W;  // padded element q is row[q - 1]
            for (std::int64_t i = 0; i <= n; ++i) {
              const std::int64_t qe = 2 * i - 1, qo = 2 * i;
              e[i] = qe >= 0 && qe < W ? row[qe] : 0.f;
              o[i] = qo < W ? row[qo] : 0.f;
            }
          }
          float* h0 = h + (4 * r) * n;
          float* h1 = h0 + n;
          float* h2 = h1 + n;
          float* h3 = h2 + n;
          for (std::int64_t t = 0; t < n; ++t) {  // d B, row r
            h0[t] = e[t] - e[t + 1];
            h1[t] = o[t] + e[t + 1];
            h2[t] = e[t + 1] - o[t];
            h3[t] = o[t] - o[t + 1];
          }
        }
        for (std::int64_t j = 0; j < 4; ++j) {  // B^T (d B), column j
          const float* r0 = h + (0 * 4 + j) * n;
          const float* r1 = h + (1 * 4 + j) * n;
          const float* r2 = h + (2 * 4 + j) * n;
          const float* r3 = h + (3 * 4 + j) * n;
          float* v0 = v + (0 * 4 + j) * plane + c * T + ty * n;
          float* v1 = v0 + 4 * plane;
          float* v2 = v1 + 4 * plane;
          float* v3 = v2 + 4 * plane;
          for (std::int64_t t = 0; t < n; ++t) {
            v0[t] = r0[t] - r2[t];
            v1[t] = r1[t] + r2[t];
            v2[t] = r2[t] - r1[t];
            v3[t] = r1[t] - r3[t];
          }
        }
      }
  }
}

// out[o][2ty + a][2tx + b] = act(bias[o] + (A^T m A)[a][b]) with m[e] = M[e][o][t]; outputs past
// the map's edge (odd H or W) are dropped.
template <class Act>
void transform_output(const float* m, std::int64_t cout, std::int64_t H, std::int64_t W, const Tiling& tl,
                      const float* bias, Act act, float* out) {
  const std::int64_t n = tl.cols, T = tl.count(), plane = cout * T;
#pragma omp parallel
  {
    std::vector<float> scratch(static_cast<std::size_t>(8 * n + 2 * 2 * n));
#pragma omp for collapse(2) schedule(static)
    for (std::int64_t o = 0; o < cout; ++o)
      for (std::int64_t ty = 0; ty < tl.rows; ++ty) {
        float* p = scratch.data();  // [4 i][2 b][n]: m A, row i
        float* y = p + 8 * n;       // [2 a][2 b][n]
        for (std::int64_t i = 0; i < 4; ++i) {
          const float* m0 = m + (4 * i + 0) * plane + o * T + ty * n;
          const float* m1 = m0 + plane;
          const float* m2 = m1 + plane;
          const float* m3 = m2 + plane;
          float* p0 = p + (2 * i) * n;
          float* p1 = p0 + n;
          for (std::int64_t t = 0; t < n; ++t) {
            p0[t] = m0[t] + m1[t] + m2[t];
            p1[t] = m1[t] - m2[t] - m3[t];
          }
        }
        for (std::int64_t b = 0; b < 2; ++b) {  // A^T (m A), column b
          const float* q0 = p + (0 * 2 + b) * n;
          const float* q1 = p + (1 * 2 + b) * n;
          const float* q2 = p + (2 * 2 + b) * n;
          const float* q3 = p + (3 * 2 + b) * n;
          float* y0 = y + (0 * 2 + b) * n;
          float* y1 = y + (1 * 2 + b) * n;
          for (std::int64_t t = 0; t < n; ++t) {
            y0[t] = q0[t] + q1[t] + q2[t];
            y1[t] = q1[t] - q2[t] - q3[t];
          }
        }
        const simd::Batch bv(bias ? bias[o] : 0.f);
        for (std::int64_t a = 0; a < 2; ++a) {
          const std::int64_t row = 2 * ty + a;
          if (row >= H) break;
          float* dst = out + (o * H + row) * W;
          const float* ya0 = y + (2 * a + 0) * n;
          const float* ya1 = y + (2 * a + 1) * n;
          for (std::int64_t t = 0; t < n; ++t) {
            dst[2 * t] = ya0[t];
            if (2 * t + 1 < W) dst[2 * t + 1] = ya1[t];
          }
          simd::map(W, dst, [&](const simd::Batch& x) { return act(x + bv); }, dst);
        }
      }
  }
}

// Packs the right operand of a GEMM stored row-major K x N (rows `ld` apart): panels of nr
// columns, a step being one row.
struct PackRowMajor {
  const float* src;
  std::int64_t ld, nr;
  void operator()(std::int64_t n0, std::int64_t cols, std::int64_t s0, std::int64_t steps, gemm::Word* dst) const {
    for (std::int64_t j = 0; j * nr < cols; ++j)
      gemm::pack_rows(src + n0 + j * nr, ld, std::min(nr, cols - j * nr), nr, s0, steps, dst + j * nr * steps);
  }
};

// Grow-only scratch of the calling thread: the transformed weights, inputs and products.
inline float* scratch(int slot, std::int64_t n) {
  thread_local std::vector<float> buffers[3];
  auto& b = buffers[slot];
  if (static_cast<std::int64_t>(b.size()) < n) b.resize(static_cast<std::size_t>(n));
  return b.data();
}

// One image: out (cout, H, W) = act(conv3x3(in (cin, H, W), w) + bias) through the kernel family
// f (float32). w: [cout][cin][3][3], float or bf16.
template <class W, class Act>
void conv3x3(const gemm::KernelFamily& f, int threads, const float* in, std::int64_t cin, std::int64_t H,
             std::int64_t Wd, const W* w, const float* bias, std::int64_t cout, float* out, Act act) {
  const Tiling tl = tiling(H, Wd);
  const std::int64_t T = tl.count();
  float* u = scratch(0, kElems * cout * cin);
  float* v = scratch(1, kElems * cin * T);
  float* m = scratch(2, kElems * cout * T);
  transform_weights(w, cout, cin, u);
  transform_input(in, cin, H, Wd, tl, v);
  for (std::int64_t e = 0; e < kElems; ++e) {  // M[e] (cout x T) = U[e] (cout x cin) · V[e] (cin x T)
    const detail::PackActivations pack_u{f, u + e * cout * cin, cin, cin};
    const PackRowMajor pack_v{v + e * cin * T, T, f.nr};
    gemm::run_gemm(f, cout, T, cin, threads, pack_u, pack_v, m + e * cout * T, T, detail::NoEpilogue{});
  }
  transform_output(m, cout, H, Wd, tl, bias, act, out);
}

// Whether Winograd runs where it applies (3x3, one group, enough channels and pixels):
// EPONA_CPU_CONV=direct turns it off (comparisons; the im2col GEMM path then runs), =winograd
// or unset keeps it on; anything else is an error.
inline bool enabled() {
  static const bool on = [] {
    const char* env = std::getenv("EPONA_CPU_CONV");
    if (!env || !*env) return true;
    const std::string_view v(env);
    EPONA_CHECK(v == "direct" || v == "winograd", "EPONA_CPU_CONV='", v, "' is not direct or winograd");
    return v == "winograd";
  }();
  return on;
}

// Worth it: the products must be large enough for the GEMMs to run near their peak (small
// channel counts or maps spend their time in the transforms).
inline bool worthwhile(std::int64_t cin, std::int64_t cout, std::int64_t H, std::int64_t W) {
  return cin >= 64 && cout >= 64 && tiling(H, W).count() >= 64;
}

}  // namespace epona::cpu::winograd
