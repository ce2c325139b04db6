// GPU tests for epona/cuda/attention/attention.cuh: flash attention (bf16 tensor-core kernels with head
// dim 128 specialised and the generic zero-padded path, each block tiling and the short
// warp-per-head kernel, and the automatic choice; float32 kernel) against cpu::attention on
// the same (bf16-rounded) inputs: dense, causal, cross (lq != lk), additive masks with a
// fully masked row, packed QKV, the MST's frame-strided temporal layout (packed and as the
// MST calls it, its one-query last block too) and its spatial one, the four model shapes
// (VisDiT 16 x 1027, MST spatial 10 x 16 x 515, TrajDiT 8 x 530, temporal 515 x 16 x 10),
// head dims 4/24/32/64/128, unaligned strides. Outputs are poisoned first; elements outside
// the output layout must stay poisoned.
// The Hopper wgmma kernels (cp.async and TMA-fed, 64- and 128-row blocks, where the build and
// GPU have them) on lengths 1, 15, 63, 64, 65, 515, 530, 1027, full and causal, cross, packed,
// padded and frame-strided rows, the DiTs' last-single-block queries, the model's shapes, and
// Auto's choice (wgmma where it applies, the mma.sync kernels elsewhere; forcing those still
// runs them), with the same bf16 bounds as the mma.sync kernels (below).
// Bounds. float32: rel_l2 and max|err| / max|v| <= 1e-5. bf16: P is rounded to bf16 before
// P·V (|δp| <= 2^-8 p, so |err| <= 2^-8 max|v|) and the output once more (2^-8 |o| <= 2^-8
// max|v|): max|err| <= 2^-7 max|v|; rel_l2 <= 1e-2 (rounding errors average out; measured
// about 2e-3).
#include "cuda_test_util.cuh"

#include <algorithm>
#include <limits>
#include <vector>

#include "epona/cuda/runtime/graph.hpp"

using namespace epona;
using namespace epona::test;

namespace {

// Where q, k, v (one input buffer, at offsets) and o (one output buffer) live.
struct Layout {
  std::int64_t seqs, heads, lq, lk, dim;
  std::int64_t q_off, q_seq, q_row, k_off, k_seq, k_row, v_off, v_seq, v_row, o_seq, o_row;
  bool causal = false;
  bool additive = false;
};

std::int64_t extent(std::int64_t off, std::int64_t seq, std::int64_t row, std::int64_t seqs, std::int64_t len,
                    const Layout& l) {
  if (seqs == 0 || len == 0) return off;
  return off + (seqs - 1) * seq + (len - 1) * row + l.heads * l.dim;
}

// Separate dense (seqs, L, heads, dim) tensors for q, k, v and o.
Layout dense(std::int64_t seqs, std::int64_t heads, std::int64_t lq, std::int64_t lk, std::int64_t dim) {
  const std::int64_t w = heads * dim;
  return {seqs, heads, lq, lk, dim, 0, lq * w, w, seqs * lq * w, lk * w, w, seqs * lq * w + seqs * lk * w, lk * w, w,
          lq * w, w};
}

// Packed (seqs, L, 3, heads, dim) QKV as the DiTs' qkv Linear writes it; o rows `o_pad` wider.
Layout packed(std::int64_t seqs, std::int64_t heads, std::int64_t len, std::int64_t dim, std::int64_t o_pad = 0) {
  const std::int64_t w = heads * dim, row = 3 * w;
  return {seqs, heads, len, len, dim, 0, len * row, row, w, len * row, row, 2 * w, len * row, row,
          len * (w + o_pad), w + o_pad};
}

// The MST's temporal attention: tokens (frames, spatial, 3C); one sequence per spatial
// position runs over the frames, so the row stride is a whole frame.
Layout temporal(std::int64_t frames, std::int64_t spatial, std::int64_t heads, std::int64_t dim) {
  const std::int64_t c = heads * dim, row = 3 * c;
  return {spatial, heads, frames, frames, dim, 0, row, spatial * row, c, row, spatial * row, 2 * c, row,
          spatial * row, c, spatial * c, true, false};
}

// The MST's temporal attention as mst.hpp calls it: separate (frames, spatial, heads, dim)
// q, k, v and o; one sequence per spatial position over the frames, causal. last_only: the
// last block's variant, one query (the last frame) over all frames, unmasked.
Layout mst_temporal(std::int64_t frames, std::int64_t spatial, std::int64_t heads, std::int64_t dim, bool last_only) {
  const std::int64_t c = heads * dim, plane = frames * spatial * c;
  Layout l{spatial, heads, frames, frames, dim, 0, c, spatial * c, plane, c, spatial * c, 2 * plane, c,
           spatial * c, c, spatial * c, true, false};
  if (last_only) {
    l.lq = 1, l.causal = false;
    l.q_off = (frames - 1) * spatial * c, l.q_row = 0;
    l.o_row = 0;
  }
  return l;
}

// Packed QKV whose queries are the last len - q_first rows (the DiTs' last single block:
// every row gives keys and values, only the target rows are queried).
Layout packed_tail(std::int64_t seqs, std::int64_t heads, std::int64_t len, std::int64_t q_first, std::int64_t dim) {
  Layout l = packed(seqs, heads, len, dim);
  l.lq = len - q_first;
  l.q_off = q_first * l.q_row;
  l.o_seq = l.lq * l.o_row;
  return l;
}

using cuda::detail::FlashKernel;
constexpr FlashKernel kBlockKernels[] = {FlashKernel::Rows64, FlashKernel::Rows128,
                                         FlashKernel::Rows64Split4};

cuda::AttentionShape device_shape(const Layout& l, const float* additive_mask) {
  cuda::AttentionShape ga;
  ga.seqs = l.seqs, ga.heads = l.heads, ga.lq = l.lq, ga.lk = l.lk, ga.head_dim = l.dim;
  ga.q_seq = l.q_seq, ga.q_row = l.q_row, ga.k_seq = l.k_seq, ga.k_row = l.k_row;
  ga.v_seq = l.v_seq, ga.v_row = l.v_row, ga.o_seq = l.o_seq, ga.o_row = l.o_row;
  ga.mask = l.causal ? cuda::Mask::Causal : cuda::Mask::None;
  ga.additive_mask = additive_mask;
  return ga;
}

std::int64_t input_elems(const Layout& l) {
  return std::max({extent(l.q_off, l.q_seq, l.q_row, l.seqs, l.lq, l), extent(l.k_off, l.k_seq, l.k_row, l.seqs, l.lk, l),
                   extent(l.v_off, l.v_seq, l.v_row, l.seqs, l.lk, l), std::int64_t{1}});
}
std::int64_t output_elems(const Layout& l) { return std::max(extent(0, l.o_seq, l.o_row, l.seqs, l.lq, l), std::int64_t{1}); }

// Runs the GPU kernel on `in` (uploaded as T) into a poisoned output and compares with `ref`
// (NaN where the output layout has no element: those must stay poisoned). plan: the planned
// TMA kernel's (its partial-result buffer is poisoned too, so that a slot the combine reads
// but no block wrote shows).
template <class T>
void compare_gpu(cuda::Context& ctx, const Layout& l, const HostF& in, const float* dmask, const HostF& ref,
                 const std::string& name, FlashKernel kernel, const cuda::detail::TmaPlan* plan = nullptr) {
  auto din = upload<T>(ctx, in);
  Dev<T> dout({output_elems(l)});
  poison(ctx, dout);
  if (plan)
    EPONA_CUDA_CHECK(cudaMemsetAsync(cuda::detail::split_partial_buffer(ctx), 0xFF,
                                     cuda::detail::kSplitPartialBytes, ctx.stream()));
  const cuda::AttentionShape ga = device_shape(l, dmask);
  try {
    cuda::detail::attention(ctx, din.data() + l.q_off, din.data() + l.k_off, din.data() + l.v_off, dout.data(), ga,
                            kernel, plan);
  } catch (const epona::Error& e) {
    // A TMA kernel may refuse strides the driver cannot describe; Auto then runs another kernel.
    const bool refused = std::string(e.what()).find("cannot describe") != std::string::npos;
    CHECK_MESSAGE(refused, e.what());
    if (refused) MESSAGE((name + ": " + e.what()));
    return;
  }
  const HostF out = download(ctx, dout);

  const auto written = [&](std::int64_t i) { return !std::isnan(ref.data()[i]); };
  const auto d = measure(out.data(), ref.data(), out.numel(), written);
  std::int64_t stray = 0;
  for (std::int64_t i = 0; i < out.numel(); ++i) stray += !written(i) && !std::isnan(out.data()[i]);
  constexpr double max_v = 2.0;  // inputs are uniform in [-2, 2)
  const Bound b = std::is_same_v<T, float> ? Bound{kF32Tol, kF32Tol * max_v} : Bound{1e-2, 2 * kBf16Roundoff * max_v};
  std::string what = std::string("attention ") + type_name<T>() + " " + name + " d=" + std::to_string(l.dim) +
                     (l.causal ? " causal" : "") + (dmask ? " +mask" : "");
  if (std::is_same_v<T, bf16> && kernel != FlashKernel::Auto)
    what += std::string(" [") + cuda::detail::flash_kernel_name(kernel) + "]";
  if (plan)
    what += " plan{rows " + std::to_string(plan->rows) + ", splits " + std::to_string(plan->splits) +
            (plan->tail_only ? ", tail only" : "") + (plan->share_rows ? "" : ", unshared") +
            (plan->narrow_last ? "" : ", wide last") + "}";
  if (l.lq > 0 && l.seqs > 0) {
    check_error(d, b, what);
  } else {
    CHECK(d.n == 0);
  }
  CHECK_MESSAGE(stray == 0, what);
}

template <class T>
void check_attention(cuda::Context& ctx, const Layout& l, std::uint32_t seed, const std::string& name,
                     FlashKernel kernel = FlashKernel::Auto) {
  cpu::Context cctx;
  HostF in = random_tensor({input_elems(l)}, seed, -2.f, 2.f);
  round_to<T>(in);
  HostF mask;
  if (l.additive) {
    mask = random_tensor({std::max<std::int64_t>(l.lq * l.lk, 1)}, seed + 1, -3.f, 3.f);
    const float inf = std::numeric_limits<float>::infinity();
    for (std::int64_t i = 0; i < l.lq; ++i)
      for (std::int64_t j = 0; j < l.lk; ++j)
        if ((i + 2 * j) % 7 == 3 || i == std::min<std::int64_t>(5, l.lq - 1)) mask.data()[i * l.lk + j] = -inf;
  }

  cpu::AttentionShape ca;
  ca.seqs = l.seqs, ca.heads = l.heads, ca.lq = l.lq, ca.lk = l.lk, ca.head_dim = l.dim;
  ca.q_seq = l.q_seq, ca.q_row = l.q_row, ca.k_seq = l.k_seq, ca.k_row = l.k_row;
  ca.v_seq = l.v_seq, ca.v_row = l.v_row, ca.o_seq = l.o_seq, ca.o_row = l.o_row;
  ca.mask = l.causal ? cpu::Mask::Causal : cpu::Mask::None;
  ca.additive_mask = l.additive ? mask.data() : nullptr;
  HostF ref({output_elems(l)});
  std::fill_n(ref.data(), ref.numel(), std::numeric_limits<float>::quiet_NaN());
  cpu::attention(cctx, in.data() + l.q_off, in.data() + l.k_off, in.data() + l.v_off, ref.data(), ca);

  auto dmask = l.additive ? upload<float>(ctx, mask) : Dev<float>();
  compare_gpu<T>(ctx, l, in, l.additive ? dmask.data() : nullptr, ref, name, kernel);
}

// Attention over `in` in float64 (softmax(q kᵀ / sqrt(dim)) v per row; causal: keys <= the
// query's row; no keys: zeros), NaN outside the output layout.
HostF reference_f64(const Layout& l, const HostF& in) {
  HostF ref({output_elems(l)});
  std::fill_n(ref.data(), ref.numel(), std::numeric_limits<float>::quiet_NaN());
  const double scale = 1.0 / std::sqrt(static_cast<double>(l.dim));
  const std::int64_t rows = l.seqs * l.heads * l.lq;
#pragma omp parallel for schedule(dynamic, 8)
  for (std::int64_t r = 0; r < rows; ++r) {
    const std::int64_t s = r / (l.heads * l.lq), h = r / l.lq % l.heads, i = r % l.lq;
    const float* q = in.data() + l.q_off + s * l.q_seq + i * l.q_row + h * l.dim;
    const std::int64_t keys = l.causal ? std::min(l.lk, i + 1) : l.lk;
    std::vector<double> p(static_cast<std::size_t>(keys));
    double mx = -std::numeric_limits<double>::infinity(), sum = 0;
    for (std::int64_t j = 0; j < keys; ++j) {
      const float* k = in.data() + l.k_off + s * l.k_seq + j * l.k_row + h * l.dim;
      double dot = 0;
      for (std::int64_t c = 0; c < l.dim; ++c) dot += double(q[c]) * k[c];
      p[j] = dot * scale;
      mx = std::max(mx, p[j]);
    }
    for (auto& x : p) sum += (x = std::exp(x - mx));
    float* o = ref.data() + s * l.o_seq + i * l.o_row + h * l.dim;
    for (std::int64_t c = 0; c < l.dim; ++c) {
      double acc = 0;
      for (std::int64_t j = 0; j < keys; ++j) acc += p[j] * in.data()[l.v_off + s * l.v_seq + j * l.v_row + h * l.dim + c];
      o[c] = keys ? static_cast<float>(acc / sum) : 0.f;
    }
  }
  return ref;
}

// One bf16 layout (random inputs, float64 reference built once) against every plan given.
void check_plans(cuda::Context& ctx, const Layout& l, std::uint32_t seed, const std::string& name,
                 const std::vector<cuda::detail::TmaPlan>& plans) {
  HostF in = random_tensor({input_elems(l)}, seed, -2.f, 2.f);
  round_to<bf16>(in);
  const HostF ref = reference_f64(l, in);
  const auto params = cuda::detail::flash_params<bf16>(nullptr, nullptr, nullptr, nullptr, device_shape(l, nullptr));
  for (const auto& plan : plans) {
    // Plans whose partial results exceed the buffer are refused (the last case checks that).
    const auto grid = cuda::detail::tma_grid(params, l.seqs, l.heads, plan);
    if (cuda::detail::tma_partial_bytes(grid, params) > cuda::detail::kSplitPartialBytes) continue;
    compare_gpu<bf16>(ctx, l, in, nullptr, ref, name, FlashKernel::TmaPlanned, &plan);
  }
}

}  // namespace

TEST_CASE_TEMPLATE("cuda attention head dim 128: dense, causal, cross, masked", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_attention<T>(ctx, dense(2, 3, 77, 77, 128), 10, "dense");
  Layout c = dense(1, 2, 100, 100, 128);
  c.causal = true;
  check_attention<T>(ctx, c, 11, "dense");
  check_attention<T>(ctx, dense(2, 2, 33, 70, 128), 12, "cross lq<lk");
  check_attention<T>(ctx, dense(1, 2, 130, 20, 128), 13, "cross lq>lk");
  Layout cc = dense(1, 1, 33, 70, 128);
  cc.causal = true;
  check_attention<T>(ctx, cc, 14, "cross lq<lk");
  Layout m = dense(2, 2, 90, 90, 128);
  m.additive = true;
  check_attention<T>(ctx, m, 15, "dense");
  m.causal = true;
  check_attention<T>(ctx, m, 16, "dense");
  check_attention<T>(ctx, dense(1, 1, 1, 1, 128), 17, "single");
  check_attention<T>(ctx, dense(3, 2, 1, 65, 128), 18, "one query");
  check_attention<T>(ctx, dense(1, 2, 5, 0, 128), 19, "no keys (zeros)");
}

TEST_CASE_TEMPLATE("cuda attention on packed QKV, MST temporal and spatial layouts", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  check_attention<T>(ctx, packed(2, 2, 131, 128, /*o_pad=*/40), 20, "packed qkv, padded o");
  Layout pc = packed(1, 3, 67, 128);
  pc.causal = true;
  check_attention<T>(ctx, pc, 21, "packed qkv");
  check_attention<T>(ctx, temporal(10, 37, 2, 128), 22, "MST temporal (10 frames x 37)");
  // MST spatial: one sequence per frame, rows are tokens of the frame.
  const std::int64_t frames = 3, tokens = 131, heads = 2, c = heads * 128, row = 3 * c;
  Layout sp{frames, heads, tokens, tokens, 128, 0, tokens * row, row, c, tokens * row, row, 2 * c, tokens * row, row,
            tokens * c, c};
  check_attention<T>(ctx, sp, 23, "MST spatial (3 frames x 131)");
  check_attention<T>(ctx, dense(2, 2, 515, 515, 128), 24, "515 tokens");
}

TEST_CASE_TEMPLATE("cuda attention generic head dims and unaligned strides", T, float, bf16) {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 30;
  for (std::int64_t dim : {4, 24, 32, 64}) {
    check_attention<T>(ctx, dense(2, 2, 45, 45, dim), seed++, "dense");
    Layout p = packed(1, 3, 70, dim, 8);
    p.causal = true;
    check_attention<T>(ctx, p, seed++, "packed qkv");
    Layout m = dense(1, 2, 40, 75, dim);
    m.additive = true;
    check_attention<T>(ctx, m, seed++, "cross");
    check_attention<T>(ctx, temporal(10, 9, 2, dim), seed++, "MST temporal");
  }
  // Head dim 128 with rows not 16-byte aligned: the generic path at 128.
  Layout u = dense(1, 2, 70, 70, 128);
  u.q_row = u.k_row = u.v_row = u.o_row = 2 * 128 + 4;
  u.q_seq = u.o_seq = 70 * u.q_row;
  u.k_seq = u.v_seq = 70 * u.k_row;
  u.k_off = u.q_seq, u.v_off = 2 * u.q_seq;
  u.causal = true;
  check_attention<T>(ctx, u, seed++, "unaligned rows");
}

// The model's four shapes with every kernel that may run them (large: device_run.sh leaves
// this case out of the sanitizer runs, which check the same code paths on the smaller cases).
TEST_CASE("cuda attention bf16 model shapes: every kernel") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 300;
  for (const FlashKernel kernel : {FlashKernel::Auto, FlashKernel::Rows64,
                                   FlashKernel::Rows128, FlashKernel::Rows64Split4}) {
    check_attention<bf16>(ctx, packed(1, 16, 1027, 128), seed++, "VisDiT joint 16 x 1027", kernel);
    check_attention<bf16>(ctx, packed(10, 16, 515, 128), seed++, "MST spatial 10 x 16 x 515", kernel);
    check_attention<bf16>(ctx, packed(1, 8, 530, 128, /*o_pad=*/24), seed++, "TrajDiT joint 8 x 530", kernel);
  }
  for (const FlashKernel kernel : {FlashKernel::Auto, FlashKernel::Short}) {
    check_attention<bf16>(ctx, mst_temporal(10, 515, 16, 128, false), seed++, "MST temporal 515 x 16 x 10", kernel);
    check_attention<bf16>(ctx, mst_temporal(10, 515, 16, 128, true), seed++, "MST temporal, last frame", kernel);
  }
}

TEST_CASE("cuda attention bf16: every block tiling on masks and odd lengths") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 100;
  for (const FlashKernel kernel : kBlockKernels) {
    check_attention<bf16>(ctx, packed(1, 3, 1027, 128), seed++, "VisDiT joint 3 heads x 1027", kernel);
    check_attention<bf16>(ctx, packed(2, 2, 515, 128, /*o_pad=*/24), seed++, "2 x 2 x 515", kernel);
    Layout c = packed(2, 3, 300, 128);
    c.causal = true;
    check_attention<bf16>(ctx, c, seed++, "packed qkv 300", kernel);
    check_attention<bf16>(ctx, dense(2, 2, 33, 70, 128), seed++, "cross lq<lk", kernel);
    check_attention<bf16>(ctx, dense(1, 2, 257, 20, 128), seed++, "cross lq>lk", kernel);
    Layout cc = dense(1, 2, 150, 190, 128);
    cc.causal = true;
    check_attention<bf16>(ctx, cc, seed++, "cross lq<lk", kernel);
    Layout m = dense(2, 2, 129, 97, 128);
    m.additive = true;
    check_attention<bf16>(ctx, m, seed++, "cross", kernel);
    m.causal = true;
    check_attention<bf16>(ctx, m, seed++, "cross", kernel);
    check_attention<bf16>(ctx, dense(3, 2, 1, 65, 128), seed++, "one query", kernel);
    check_attention<bf16>(ctx, dense(1, 2, 5, 0, 128), seed++, "no keys (zeros)", kernel);
    check_attention<bf16>(ctx, temporal(10, 37, 2, 128), seed++, "MST temporal (10 frames x 37)", kernel);
    for (std::int64_t dim : {24, 64}) {
      Layout p = packed(1, 3, 140, dim, 8);
      p.causal = true;
      check_attention<bf16>(ctx, p, seed++, "packed qkv", kernel);
    }
  }
}

TEST_CASE("cuda attention bf16: the short kernel (MST temporal) and its automatic choice") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  std::uint32_t seed = 200;
  for (const FlashKernel kernel : {FlashKernel::Short, FlashKernel::Auto}) {
    check_attention<bf16>(ctx, mst_temporal(10, 37, 4, 128, false), seed++, "MST temporal 37 x 4 x 10", kernel);
    check_attention<bf16>(ctx, mst_temporal(10, 37, 4, 128, true), seed++, "MST temporal, last frame", kernel);
    check_attention<bf16>(ctx, temporal(10, 37, 3, 128), seed++, "MST temporal packed", kernel);
    check_attention<bf16>(ctx, temporal(16, 11, 2, 128), seed++, "16 frames", kernel);
    check_attention<bf16>(ctx, temporal(1, 5, 2, 128), seed++, "1 frame", kernel);
    check_attention<bf16>(ctx, dense(3, 5, 13, 16, 128), seed++, "cross lq<lk", kernel);
    check_attention<bf16>(ctx, dense(3, 5, 16, 7, 128), seed++, "cross lq>lk", kernel);
    Layout m = dense(2, 3, 11, 14, 128);
    m.additive = true;
    check_attention<bf16>(ctx, m, seed++, "cross", kernel);
    m.causal = true;
    check_attention<bf16>(ctx, m, seed++, "cross", kernel);
    check_attention<bf16>(ctx, dense(1, 2, 5, 0, 128), seed++, "no keys (zeros)", kernel);
    for (std::int64_t dim : {4, 24, 64, 100}) {
      check_attention<bf16>(ctx, temporal(10, 9, 2, dim), seed++, "MST temporal", kernel);
      check_attention<bf16>(ctx, mst_temporal(10, 7, 2, dim, true), seed++, "MST temporal, last frame", kernel);
    }
  }
  // Past 16 keys (or queries) the short kernel is refused, and Auto takes a block kernel.
  Dev<bf16> buf({64 * 128});
  cuda::AttentionShape a;
  a.lq = 4, a.lk = 17, a.head_dim = 128, a.q_row = a.k_row = a.v_row = a.o_row = 128;
  CHECK_THROWS_WITH_AS(cuda::detail::attention(ctx, buf.data(), buf.data(), buf.data(), buf.data(), a,
                                               FlashKernel::Short),
                       doctest::Contains("short kernel"), epona::Error);
  check_attention<bf16>(ctx, dense(2, 2, 17, 17, 128), seed++, "17 frames");
  check_attention<bf16>(ctx, dense(2, 2, 3, 40, 128), seed++, "3 queries x 40 keys");
}

TEST_CASE("cuda attention rejects unsupported shapes with epona::Error") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  Dev<bf16> buf({1024});
  cuda::AttentionShape a;
  a.lq = a.lk = 2, a.head_dim = 130;
  CHECK_THROWS_WITH_AS(cuda::attention(ctx, buf.data(), buf.data(), buf.data(), buf.data(), a),
                       doctest::Contains("head_dim 130"), epona::Error);
  a.head_dim = 64, a.heads = 70000;
  CHECK_THROWS_AS(cuda::attention(ctx, buf.data(), buf.data(), buf.data(), buf.data(), a), epona::Error);
  a.heads = 1, a.lq = -1;
  CHECK_THROWS_AS(cuda::attention(ctx, buf.data(), buf.data(), buf.data(), buf.data(), a), epona::Error);
}

// The Hopper kernel exists only in sm_90a builds running on a 9.0 GPU; elsewhere these pass
// with a message.
#define EPONA_REQUIRE_WGMMA(ctx)                                                      \
  do {                                                                                \
    if (!cuda::detail::flash_wgmma_available(ctx)) {                                  \
      MESSAGE("no wgmma kernel in this build or on this GPU (needs sm_90a): skipping"); \
      return;                                                                         \
    }                                                                                 \
  } while (0)

constexpr FlashKernel kWgmmaKernels[] = {FlashKernel::Wgmma64, FlashKernel::Tma64, FlashKernel::Tma128,
                                         FlashKernel::TmaPlanned};

TEST_CASE("cuda attention bf16: the wgmma kernel on awkward lengths, masks and layouts") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  EPONA_REQUIRE_WGMMA(ctx);
  std::uint32_t seed = 400;
  for (const FlashKernel kernel : kWgmmaKernels) {
    for (const std::int64_t len : {1, 15, 63, 64, 65, 515, 530, 1027}) {
      const std::string name = "packed qkv " + std::to_string(len);
      check_attention<bf16>(ctx, packed(2, 3, len, 128, /*o_pad=*/len % 2 ? 8 : 0), seed++, name, kernel);
      Layout c = packed(2, 2, len, 128);
      c.causal = true;
      check_attention<bf16>(ctx, c, seed++, name, kernel);
    }
    struct Cross { std::int64_t lq, lk; };
    for (const Cross x : {Cross{15, 530}, Cross{512, 1027}, Cross{1, 65}, Cross{65, 1}, Cross{130, 20},
                          Cross{33, 70}, Cross{200, 129}}) {
      const std::string name = "cross " + std::to_string(x.lq) + " x " + std::to_string(x.lk);
      check_attention<bf16>(ctx, dense(2, 2, x.lq, x.lk, 128), seed++, name, kernel);
      Layout c = dense(1, 3, x.lq, x.lk, 128);
      c.causal = true;
      check_attention<bf16>(ctx, c, seed++, name, kernel);
    }
    check_attention<bf16>(ctx, packed_tail(1, 4, 530, 515, 128), seed++, "last single block 15 of 530", kernel);
    check_attention<bf16>(ctx, temporal(10, 37, 2, 128), seed++, "MST temporal (10 frames x 37)", kernel);
    check_attention<bf16>(ctx, mst_temporal(10, 37, 2, 128, true), seed++, "MST temporal, last frame", kernel);
    check_attention<bf16>(ctx, dense(1, 2, 5, 0, 128), seed++, "no keys (zeros)", kernel);
  }
}

// Large: like the model-shape case above, left out of the sanitizer runs.
TEST_CASE("cuda attention bf16 model shapes: the wgmma kernel") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  EPONA_REQUIRE_WGMMA(ctx);
  std::uint32_t seed = 500;
  for (const FlashKernel kernel : kWgmmaKernels) {
    check_attention<bf16>(ctx, packed(1, 16, 1027, 128), seed++, "VisDiT joint 16 x 1027", kernel);
    check_attention<bf16>(ctx, packed_tail(1, 16, 1027, 515, 128), seed++, "VisDiT last single 512 of 1027", kernel);
    check_attention<bf16>(ctx, packed(10, 16, 515, 128), seed++, "MST spatial 10 x 16 x 515", kernel);
    check_attention<bf16>(ctx, packed(1, 8, 530, 128, /*o_pad=*/24), seed++, "TrajDiT joint 8 x 530", kernel);
    check_attention<bf16>(ctx, packed_tail(1, 8, 530, 515, 128), seed++, "TrajDiT last single 15 of 530", kernel);
  }
}

TEST_CASE("cuda attention bf16: Auto takes the wgmma kernel where it applies, the others elsewhere") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const bool wgmma = cuda::detail::flash_wgmma_available(ctx);
  MESSAGE((std::string("wgmma kernels available: ") + (wgmma ? "yes" : "no")));
  Dev<bf16> buf({4 * 1027 * 3 * 128 + 64});
  bf16* d = buf.data();
  cuda::AttentionShape a;
  a.heads = 1, a.lq = a.lk = 530, a.head_dim = 128;
  a.q_row = a.k_row = a.v_row = 3 * 128, a.o_row = 128;
  a.q_seq = a.k_seq = a.v_seq = 530 * 3 * 128, a.o_seq = 530 * 128;
  const auto pick = [&](const bf16* q) { return cuda::detail::auto_flash_kernel(ctx, q, d + 128, d + 256, d, a); };
  CHECK(cuda::detail::is_wgmma(pick(d)) == wgmma);
  if (wgmma) {
    const bool saved = ctx.policy().attention_split;
    ctx.policy().attention_split = false;
    CHECK(pick(d) == FlashKernel::Tma64);  // 9 blocks of 64 rows: one wave
    a.heads = 4, a.seqs = 40;              // 1440 blocks of 64 rows, more than a wave: 128-row blocks
    CHECK(pick(d) == FlashKernel::Tma128);
    ctx.policy().attention_split = true;
    CHECK(pick(d) == FlashKernel::TmaPlanned);
    // Auto's plans: 128-row blocks over many waves; the short last row blocks cut into key ranges
    // where they alone would make a second wave; 64-row blocks within a wave, keys cut into
    // ranges where few blocks leave multiprocessors idle.
    const auto plan = [&] {
      const auto p = cuda::detail::flash_params<bf16>(d, d + 128, d + 256, d, a);
      return cuda::detail::auto_tma_plan(ctx, p, a.seqs, a.heads);
    };
    CHECK(plan().rows == 128);
    CHECK(plan().splits == 1);  // 640 full blocks: the short ones fill the last wave as they are
    a.heads = 16, a.seqs = 1, a.lq = a.lk = 1027;  // 128 full blocks + 16 short ones: those are cut
    CHECK(plan().rows == 128);
    CHECK((plan().tail_only && plan().splits > 1));
    a.lq = a.lk = 530;
    a.heads = 8, a.seqs = 1;
    CHECK(plan().rows == 64);
    a.lq = 15;
    CHECK(plan().rows == 64);
    CHECK(plan().splits > 1);  // 8 blocks of 15 rows: the keys are cut into ranges
    a.lq = 530;
    ctx.policy().attention_split = saved;
    a.heads = 1, a.seqs = 1;
  }
  CHECK(!cuda::detail::is_wgmma(pick(d + 1)));  // rows not 16-byte aligned: the generic path
  a.lq = a.lk = 10;
  CHECK(pick(d) == FlashKernel::Short);
  a.lq = a.lk = 530;
  a.head_dim = 64;
  CHECK(pick(d) == FlashKernel::Rows64Split4);  // 9 row blocks of 64 < the multiprocessors
  a.head_dim = 128;
  Dev<float> mask({530 * 530});
  a.additive_mask = mask.data();
  CHECK(!cuda::detail::is_wgmma(pick(d)));
  if (wgmma) {
    for (const FlashKernel kernel : kWgmmaKernels)
      CHECK_THROWS_WITH_AS(cuda::detail::attention(ctx, d, d + 128, d + 256, d, a, kernel),
                           doctest::Contains("wgmma"), epona::Error);
  }
  // With the wgmma kernel picked by Auto, the mma.sync kernels still run when forced (their
  // own cases above run the same layouts with every kernel named).
  std::uint32_t seed = 600;
  for (const FlashKernel kernel : {FlashKernel::Auto, FlashKernel::Rows64, FlashKernel::Rows64Split4})
    check_attention<bf16>(ctx, packed(2, 2, 530, 128), seed++, "packed qkv 530", kernel);
}

// The planned TMA kernel (TmaPlanned): each way a plan covers a call. 64-row blocks (the two
// consumers share the rows and take alternate key tiles) and 128-row blocks (a last row block of
// <= 64 rows shared), key ranges (float32 partials and the combine kernel) on every row block or
// the last only, unshared rows, the wide last tile and persistent CTAs that take several row
// blocks each; against float64 loops, with the bf16 bound above.
using cuda::detail::TmaPlan;
std::vector<TmaPlan> every_plan() {
  return {TmaPlan{64, 1},          TmaPlan{64, 2},        TmaPlan{64, 3},         TmaPlan{64, 5},
          TmaPlan{128, 1, true},   TmaPlan{128, 3, true}, TmaPlan{128, 2},        TmaPlan{128, 4},
          TmaPlan{128, 16},        TmaPlan{64, 2, false, false, false},       TmaPlan{128, 3, true, false, true},
          // persistent: few CTAs, so each takes many row blocks (shared, split and whole ones in turn)
          TmaPlan{128, 1, true, true, true, 3}, TmaPlan{64, 3, false, true, true, 5},
          TmaPlan{128, 2, false, true, true, 7}, TmaPlan{128, 3, true, false, true, 2}};
}

TEST_CASE("cuda attention bf16: the planned TMA kernel, every plan on awkward lengths") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  EPONA_REQUIRE_WGMMA(ctx);
  const auto plans = every_plan();
  std::uint32_t seed = 700;
  for (const std::int64_t len : {1, 3, 15, 64, 65, 130, 515, 530}) {
    const std::string name = "packed qkv 8 heads x " + std::to_string(len);
    check_plans(ctx, packed(1, 8, len, 128, /*o_pad=*/len % 2 ? 8 : 0), seed++, name, plans);
    Layout c = packed(2, 3, len, 128);
    c.causal = true;
    check_plans(ctx, c, seed++, "packed qkv 2 x 3 heads x " + std::to_string(len), plans);
  }
  check_plans(ctx, packed(2, 2, 1027, 128), seed++, "packed qkv 2 x 2 heads x 1027", plans);
  Layout c = packed(1, 3, 1027, 128);
  c.causal = true;
  check_plans(ctx, c, seed++, "packed qkv 3 heads x 1027", plans);
  struct Cross { std::int64_t lq, lk; };
  for (const Cross x : {Cross{15, 530}, Cross{3, 1027}, Cross{1, 65}, Cross{65, 1}, Cross{130, 20}, Cross{200, 129}}) {
    const std::string name = "cross " + std::to_string(x.lq) + " x " + std::to_string(x.lk);
    check_plans(ctx, dense(2, 2, x.lq, x.lk, 128), seed++, name, plans);
    Layout cc = dense(1, 3, x.lq, x.lk, 128);
    cc.causal = true;
    check_plans(ctx, cc, seed++, name, plans);
  }
  check_plans(ctx, packed_tail(1, 8, 530, 515, 128), seed++, "TrajDiT last single block 15 of 530", plans);
  check_plans(ctx, temporal(10, 37, 2, 128), seed++, "MST temporal (10 frames x 37)", plans);
  check_plans(ctx, mst_temporal(10, 37, 2, 128, true), seed++, "MST temporal, last frame", plans);
}

// Large: left out of the sanitizer runs, like the other model-shape cases.
TEST_CASE("cuda attention bf16 model shapes: the planned TMA kernel") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  EPONA_REQUIRE_WGMMA(ctx);
  const int sms = ctx.info().multiprocessors;
  const std::vector<TmaPlan> plans = {TmaPlan{64, 1},        TmaPlan{64, 3},  TmaPlan{128, 1, true},
                                      TmaPlan{128, 5, true}, TmaPlan{128, 2}, TmaPlan{64, 5},
                                      TmaPlan{128, 1, true, true, true, sms}, TmaPlan{128, 5, true, true, true, sms}};
  std::uint32_t seed = 800;
  check_plans(ctx, packed(1, 16, 1027, 128), seed++, "VisDiT joint 16 x 1027", plans);
  check_plans(ctx, packed_tail(1, 16, 1027, 515, 128), seed++, "VisDiT last single 512 of 1027", plans);
  check_plans(ctx, packed(10, 16, 515, 128), seed++, "MST spatial 10 x 16 x 515", plans);
  check_plans(ctx, packed(1, 16, 515, 128), seed++, "MST spatial, last block 16 x 515", plans);
  check_plans(ctx, packed(1, 8, 530, 128, /*o_pad=*/24), seed++, "TrajDiT joint 8 x 530", plans);
  check_plans(ctx, packed_tail(1, 8, 530, 515, 128), seed++, "TrajDiT last single 15 of 530", plans);
  // Auto's plan, with the switch on and off.
  const bool saved = ctx.policy().attention_split;
  for (const bool split : {true, false}) {
    ctx.policy().attention_split = split;
    const std::string name = split ? " (Auto, planned)" : " (Auto, unplanned)";
    check_attention<bf16>(ctx, packed(1, 16, 1027, 128), seed++, "VisDiT joint 16 x 1027" + name);
    check_attention<bf16>(ctx, packed(10, 16, 515, 128), seed++, "MST spatial 10 x 16 x 515" + name);
    check_attention<bf16>(ctx, packed(1, 8, 530, 128), seed++, "TrajDiT joint 8 x 530" + name);
    check_attention<bf16>(ctx, packed_tail(1, 8, 530, 515, 128), seed++, "TrajDiT last single 15 of 530" + name);
  }
  ctx.policy().attention_split = saved;
}

TEST_CASE("cuda attention bf16: planned TMA kernel in a CUDA graph, bad plans rejected") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;  // fresh: the partial-result buffer is first made while the graph records
  EPONA_REQUIRE_WGMMA(ctx);
  const Layout l = packed_tail(1, 8, 530, 515, 128);
  HostF in = random_tensor({input_elems(l)}, 900, -2.f, 2.f);
  round_to<bf16>(in);
  const HostF ref = reference_f64(l, in);
  auto din = upload<bf16>(ctx, in);
  Dev<bf16> dout({output_elems(l)});
  const TmaPlan plan{64, 3};
  const cuda::AttentionShape ga = device_shape(l, nullptr);
  cuda::GraphCache graph;
  for (int run = 0; run < 3; ++run) {  // records once, then replays
    poison(ctx, dout);
    if (run > 0)  // the first run makes the buffer while recording
      EPONA_CUDA_CHECK(cudaMemsetAsync(cuda::detail::split_partial_buffer(ctx), 0xFF,
                                       cuda::detail::kSplitPartialBytes, ctx.stream()));
    graph.run(ctx, {1}, [&] {
      cuda::detail::attention(ctx, din.data() + l.q_off, din.data() + l.k_off, din.data() + l.v_off, dout.data(), ga,
                              FlashKernel::TmaPlanned, &plan);
    });
    const HostF out = download(ctx, dout);
    const auto written = [&](std::int64_t i) { return !std::isnan(ref.data()[i]); };
    check_error(measure(out.data(), ref.data(), out.numel(), written), Bound{1e-2, 2 * kBf16Roundoff * 2.0},
                "planned TMA kernel in a graph, run " + std::to_string(run));
  }
  if (ctx.policy().graphs) CHECK(graph.captures() == 1);

  const auto run_plan = [&](const Layout& lay, TmaPlan p) {
    cuda::detail::attention(ctx, din.data(), din.data(), din.data(), dout.data(), device_shape(lay, nullptr),
                            FlashKernel::TmaPlanned, &p);
  };
  CHECK_THROWS_WITH_AS(run_plan(l, TmaPlan{96, 1}), doctest::Contains("unsupported"), epona::Error);
  CHECK_THROWS_WITH_AS(run_plan(l, TmaPlan{64, 17}), doctest::Contains("unsupported"), epona::Error);
  CHECK_THROWS_WITH_AS(run_plan(l, TmaPlan{128, 1, true, true, true, -1}), doctest::Contains("unsupported"),
                       epona::Error);
  // 1 x 8 x 530 rows x 16 ranges of partials: 35 MB, more than the buffer holds.
  Layout big = packed(1, 8, 530, 128);
  CHECK(input_elems(big) <= din.numel());
  CHECK_THROWS_WITH_AS(run_plan(big, TmaPlan{64, 16}), doctest::Contains("partial results"), epona::Error);
}

namespace {

// LayerNorm parameters of q and of k over a token's heads x dim channels.
struct QkNormParams {
  HostF q_weight, q_bias, k_weight, k_bias;
  float q_eps = 1e-5f, k_eps = 1e-6f;  // different, so that a swap shows
};

// Row r of q (or k) in float64 through its LayerNorm, rounded to bf16 in place.
void layer_norm_row_f64(float* x, std::int64_t n, const HostF& w, const HostF& b, float eps) {
  double mean = 0, var = 0;
  for (std::int64_t c = 0; c < n; ++c) mean += x[c];
  mean /= double(n);
  for (std::int64_t c = 0; c < n; ++c) var += (x[c] - mean) * (x[c] - mean);
  const double rstd = 1.0 / std::sqrt(var / double(n) + eps);
  for (std::int64_t c = 0; c < n; ++c) x[c] = float(bf16(float((x[c] - mean) * rstd * w.data()[c] + b.data()[c])));
}

// A copy of `in` with every q and every k row of the layout normalised as the model's q_norm /
// k_norm.
HostF normalise_qk_f64(const Layout& l, const HostF& raw, const QkNormParams& n) {
  HostF in = raw.clone();  // tensors share their storage when copied
  const std::int64_t c = l.heads * l.dim;
  for (std::int64_t s = 0; s < l.seqs; ++s) {
    for (std::int64_t i = 0; i < l.lq; ++i)
      layer_norm_row_f64(in.data() + l.q_off + s * l.q_seq + i * l.q_row, c, n.q_weight, n.q_bias, n.q_eps);
    for (std::int64_t j = 0; j < l.lk; ++j)
      layer_norm_row_f64(in.data() + l.k_off + s * l.k_seq + j * l.k_row, c, n.k_weight, n.k_bias, n.k_eps);
  }
  return in;
}

// attention_qk_layer_norm on `l` (q, k offset from zero mean, so that the mean matters) against
// float64 LayerNorms rounded to bf16 and float64 attention, within the bf16 attention bound;
// q and k unchanged; elements outside the output untouched; and against the separate pass
// (layer_norm in place, then attention) where q and k are dense row blocks.
void check_attention_qk_norm(cuda::Context& ctx, const Layout& l, std::uint32_t seed, const std::string& name) {
  const std::int64_t c = l.heads * l.dim;
  HostF in = random_tensor({input_elems(l)}, seed, -1.f, 3.f);
  round_to<bf16>(in);
  QkNormParams n{random_tensor({c}, seed + 1, 0.5f, 1.5f), random_tensor({c}, seed + 2),
                 random_tensor({c}, seed + 3, 0.5f, 1.5f), random_tensor({c}, seed + 4)};
  const HostF ref = reference_f64(l, normalise_qk_f64(l, in, n));
  const auto qw = upload<float>(ctx, n.q_weight), qb = upload<float>(ctx, n.q_bias);
  const auto kw = upload<float>(ctx, n.k_weight), kb = upload<float>(ctx, n.k_bias);
  auto din = upload<bf16>(ctx, in);
  Dev<bf16> dout({output_elems(l)});
  poison(ctx, dout);
  const cuda::AttentionShape ga = device_shape(l, nullptr);
  const bool ran = cuda::attention_qk_layer_norm(ctx, din.data() + l.q_off, din.data() + l.k_off, din.data() + l.v_off,
                                                 dout.data(), ga, qw.data(), qb.data(), n.q_eps, kw.data(), kb.data(),
                                                 n.k_eps);
  REQUIRE_MESSAGE(ran, name);
  const HostF out = download(ctx, dout);
  const auto written = [&](std::int64_t i) { return !std::isnan(ref.data()[i]); };
  std::int64_t stray = 0;
  for (std::int64_t i = 0; i < out.numel(); ++i) stray += !written(i) && !std::isnan(out.data()[i]);
  const Bound bound{1e-2, 2 * kBf16Roundoff * 3.0};  // |v| < 3
  check_error(measure(out.data(), ref.data(), out.numel(), written), bound, "attention + QK LayerNorm " + name);
  CHECK_MESSAGE(stray == 0, name);
  const HostF after = download(ctx, din);
  CHECK_MESSAGE(std::equal(in.data(), in.data() + in.numel(), after.data()), name, ": q or k was written");

  // The separate pass (layer_norm_rope_qk over q's and k's rows, in place), then the attention:
  // where q and k are dense row blocks (not packed QKV).
  if (l.q_row != c && l.q_row != 0 && l.q_seq != c) return;
  auto sep = upload<bf16>(ctx, in);
  Dev<bf16> sout({output_elems(l)});
  poison(ctx, sout);
  const std::int64_t rows_q = l.q_row == 0 ? l.seqs : l.seqs * l.lq, rows_k = l.seqs * l.lk;
  cuda::layer_norm(ctx, sep.data() + l.q_off, sep.data() + l.q_off, rows_q, c, qw.data(), qb.data(), n.q_eps);
  cuda::layer_norm(ctx, sep.data() + l.k_off, sep.data() + l.k_off, rows_k, c, kw.data(), kb.data(), n.k_eps);
  cuda::attention(ctx, sep.data() + l.q_off, sep.data() + l.k_off, sep.data() + l.v_off, sout.data(), ga);
  const HostF sref = download(ctx, sout);
  check_error(measure(sref.data(), ref.data(), out.numel(), written), bound, "separate norm + attention " + name);
  // The two differ only where a row's statistics, summed in another order, round an element
  // of q or k the other way: rare, so the L2 bound is tighter.
  check_error(measure(out.data(), sref.data(), out.numel(), written), Bound{1e-3, bound.abs},
              "inside vs separate " + name);

}

}  // namespace

TEST_CASE("cuda attention bf16: the QK LayerNorm inside the short kernel (MST time layers)") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  if (!cuda::detail::clusters_available(ctx)) {
    MESSAGE("no thread-block clusters in this build or on this GPU (needs sm_90): skipping");
    return;
  }
  std::uint32_t seed = 700;
  cuda::detail::attention_qk_norm_forced() = true;  // also where it does not pay (lq != lk)
  // Heads 16 = clusters of 4 CTAs (the MST), and 4 / 8 / 12 / 32: clusters of 1, 2, 3, 8.
  check_attention_qk_norm(ctx, mst_temporal(10, 37, 16, 128, false), seed += 8, "MST time layer 37 x 16 x 10");
  check_attention_qk_norm(ctx, mst_temporal(10, 37, 16, 128, true), seed += 8, "MST last block (one query)");
  for (std::int64_t heads : {4, 8, 12, 32})
    check_attention_qk_norm(ctx, mst_temporal(10, 9, heads, 128, false), seed += 8,
                            std::to_string(heads) + " heads");
  check_attention_qk_norm(ctx, temporal(16, 11, 4, 128), seed += 8, "16 frames, packed");
  check_attention_qk_norm(ctx, temporal(1, 5, 8, 128), seed += 8, "1 frame");
  check_attention_qk_norm(ctx, dense(3, 8, 13, 16, 128), seed += 8, "cross lq<lk");
  check_attention_qk_norm(ctx, dense(3, 4, 16, 7, 128), seed += 8, "cross lq>lk");
  Layout causal = dense(2, 8, 11, 11, 128);
  causal.causal = true;
  check_attention_qk_norm(ctx, causal, seed += 8, "causal");

  // Declined (false, nothing run) where the kernel does not apply; the caller then norms and
  // attends separately.
  Dev<bf16> buf({64 * 4096}), out({64 * 4096});
  Dev<float> par({4096});
  cuda::fill_bytes(ctx, buf, 0);
  cuda::fill_bytes(ctx, par, 0);
  const auto runs = [&](const cuda::AttentionShape& a, const float* w = nullptr) {
    if (!w) w = par.data();
    return cuda::attention_qk_layer_norm(ctx, buf.data(), buf.data(), buf.data(), out.data(), a, w, w, 1e-5f, w, w,
                                         1e-5f);
  };
  cuda::AttentionShape a = device_shape(dense(2, 16, 10, 10, 128), nullptr);
  CHECK(runs(a));
  cuda::detail::attention_qk_norm_forced() = false;
  cuda::AttentionShape last = device_shape(mst_temporal(10, 4, 16, 128, true), nullptr);
  CHECK_FALSE(runs(last));  // one query over 10 keys: the separate pass is faster
  CHECK(runs(a));
  cuda::AttentionShape b = a;
  b.lk = 17;
  CHECK_FALSE(runs(b));
  b = a, b.heads = 6;  // not a multiple of the 4 heads a CTA takes
  CHECK_FALSE(runs(b));
  b = a, b.heads = 36;  // clusters of 9: past the portable 8
  CHECK_FALSE(runs(b));
  b = a, b.head_dim = 64;
  CHECK_FALSE(runs(b));
  b = a, b.additive_mask = par.data();
  CHECK_FALSE(runs(b));
  CHECK_FALSE(runs(a, par.data() + 1));  // parameters not 16-byte aligned
  Dev<float> f32({64 * 4096});
  CHECK_FALSE(cuda::attention_qk_layer_norm(ctx, f32.data(), f32.data(), f32.data(), f32.data(), a, par.data(),
                                            par.data(), 1e-5f, par.data(), par.data(), 1e-5f));
  ctx.policy().attention_qk_norm = false;
  CHECK_FALSE(runs(a));
  ctx.policy().attention_qk_norm = true;
  a.seqs = -1;
  CHECK_THROWS_WITH_AS(runs(a), doctest::Contains("negative extent"), epona::Error);
  EPONA_CUDA_CHECK(cudaStreamSynchronize(ctx.stream()));
}
