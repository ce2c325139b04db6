// Tests for epona/model/dcae.hpp and epona/model/latent_layout.hpp beyond the golden parity:
// the token <-> NCHW latent layout (l = y·w + x, channels last), strict binding (missing,
// mis-shaped, unexpected keys named; BatchNorm counters ignored; temporal keys refused when the
// config has no temporal decoder), clip semantics (frame 0 of a clip = its single-frame decode,
// causality inside a clip, independence of clips), the observer's order of points, bf16
// weights, and errors for bad shapes. Weights and config: the golden set (EPONA_GOLDEN_DIR).
#include <doctest/doctest.h>

#include <cmath>
#include <cstdlib>
#include <vector>

#include "../metrics.hpp"
#include "epona/cpu/context.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "../golden_dir.hpp"

using namespace epona;
using epona::test::golden_dir;
using epona::test::rel_max;
using HostTensor = Tensor<float, Cpu>;
using Model = Dcae<Cpu, float>;

namespace {

const io::TensorMap& weights() {
  static const io::TensorMap w = io::load_safetensors(golden_dir() + "/weights_dcae.safetensors");
  return w;
}
const DcaeConfig& config() {
  static const DcaeConfig c = io::load_configs(golden_dir() + "/configs.json").dcae;
  return c;
}
const Dcae<Cpu, float>& shared_dcae() {
  static const Dcae<Cpu, float> m = Dcae<Cpu, float>::load(weights(), config());
  return m;
}

HostTensor random_latents(std::int64_t n, std::uint64_t seed) {
  HostTensor t({n, config().latent_channels, config().latent_h(), config().latent_w()});
  std::uint64_t s = seed;
  for (std::int64_t i = 0; i < t.numel(); ++i) {
    s = s * 6364136223846793005ull + 1442695040888963407ull;
    t.data()[i] = static_cast<float>(static_cast<double>(s >> 11) / 9007199254740992.0 * 4.0 - 2.0);
  }
  return t;
}

// A copy of the golden weight map with `drop` left out and `extra` entries added.
io::TensorMap edited(const std::string& drop, const std::vector<std::pair<std::string, io::RawTensor>>& extra = {}) {
  io::TensorMap m("edited weights");
  for (const auto& [name, t] : weights().entries())
    if (name != drop) m.add(name, t);
  for (const auto& [name, t] : extra) m.add(name, t);
  return m;
}

}  // namespace

TEST_CASE("latent layout: tokens (…, L, C) row-major over (h, w), channels last <-> NCHW") {
  cpu::Context ctx;
  const std::int64_t B = 2, T = 3, h = 2, w = 5, C = 4;
  HostTensor tokens({B, T, h * w, C});
  for (std::int64_t i = 0; i < tokens.numel(); ++i) tokens.data()[i] = static_cast<float>(i);
  const HostTensor z = tokens_to_latent(ctx, tokens, h, w);
  CHECK(z.shape() == Shape{B * T, C, h, w});
  for (std::int64_t n = 0; n < B * T; ++n)
    for (std::int64_t c = 0; c < C; ++c)
      for (std::int64_t y = 0; y < h; ++y)
        for (std::int64_t x = 0; x < w; ++x) CHECK(z.at(n, c, y, x) == tokens.at(n / T, n % T, y * w + x, c));
  const HostTensor back = latent_to_tokens(ctx, z);
  CHECK(back.shape() == Shape{B * T, h * w, C});
  for (std::int64_t i = 0; i < back.numel(); ++i) CHECK(back.data()[i] == tokens.data()[i]);
  const HostTensor grid = tokens_to_latent(ctx, tokens.reshape({B * T, h, w, C}), h, w);  // (N, h, w, C)
  for (std::int64_t i = 0; i < grid.numel(); ++i) CHECK(grid.data()[i] == z.data()[i]);
  CHECK_THROWS_WITH_AS(tokens_to_latent(ctx, tokens, 3, 3), doctest::Contains("expected (N, 9, C)"), Error);
}

TEST_CASE("strict binding names missing, mis-shaped and unexpected keys") {
  const std::string key = "decoder.stages.2.op_list.1.main.conv2.norm.running_var";
  REQUIRE(weights().contains(key));
  CHECK_THROWS_WITH_AS(Model::load(edited(key), config()), doctest::Contains(("missing '" + key + "'").c_str()), Error);

  const io::RawTensor& one = weights().at("encoder.project_in.conv.conv.bias");
  CHECK_THROWS_WITH_AS(Model::load(edited("", {{"decoder.surprise", one}}), config()),
                       doctest::Contains("unexpected 'decoder.surprise'"), Error);
  CHECK_NOTHROW(Model::load(edited("", {{"decoder.surprise", one}}), config(), false));
  // a counter where no BatchNorm is (the encoder uses RMSNorm2d) is not exempt
  const std::string stray = "encoder.stages.1.op_list.0.main.conv2.norm.num_batches_tracked";
  REQUIRE(!weights().contains(stray));
  const io::RawTensor& counter = weights().at("decoder.stages.1.op_list.1.main.conv2.norm.num_batches_tracked");
  CHECK_THROWS_WITH_AS(Model::load(edited("", {{stray, counter}}), config()),
                       doctest::Contains(("unexpected '" + stray + "'").c_str()), Error);

  const std::string wkey = "space_block.3.attention.wq.weight";
  io::RawTensor bad = weights().at(wkey);
  bad.shape = {bad.shape[1], bad.shape[0] / 2, 2};
  CHECK_THROWS_WITH_AS(Model::load(edited(wkey, {{wkey, bad}}), config()),
                       doctest::Contains(("'" + wkey + "' has shape").c_str()), Error);

  DcaeConfig plain = config();  // a config without the temporal decoder: its keys are unexpected
  plain.add_decoder_temporal = false;
  CHECK_THROWS_WITH_AS(Model::load(weights(), plain), doctest::Contains("unexpected 'causal_time_block.0"),
                       Error);
}

TEST_CASE("clip decode: frame 0 equals its single-frame decode; causal inside a clip; clips independent") {
  cpu::Context ctx;
  const std::int64_t Tc = config().condition_frames;
  REQUIRE(Tc >= 2);
  HostTensor clips = random_latents(2 * Tc, 11);
  const HostTensor video = shared_dcae().decode(ctx, clips, true);
  const HostTensor alone = shared_dcae().decode(ctx, clips.slice(0, 1), false);
  CHECK(rel_max(video.slice(0, 1), alone) <= 1e-5);  // same function, other GEMM row blocking
  const HostTensor single1 = shared_dcae().decode(ctx, clips.slice(1, 2), false);
  const double rel_seen = rel_max(video.slice(1, 2), single1);  // infinite on a NaN or Inf
  CHECK(std::isfinite(rel_seen));
  CHECK(rel_seen > 1e-3);  // frame 1 sees frame 0 through the time attention

  HostTensor changed = clips.clone();
  HostTensor last = changed.slice(Tc - 1, Tc);  // last frame of clip 0
  for (std::int64_t i = 0; i < last.numel(); ++i) last.data()[i] += 0.5f;
  const HostTensor video2 = shared_dcae().decode(ctx, changed, true);
  for (std::int64_t n = 0; n < 2 * Tc; ++n) {
    INFO("frame " << n);
    const bool affected = n == Tc - 1;
    const double r = rel_max(video2.slice(n, n + 1), video.slice(n, n + 1));
    if (affected) CHECK(r > 1e-3);
    else CHECK(r == 0);
  }
}

TEST_CASE("observer: encoder points in order 1..5, decoder 5..1, one call per image") {
  cpu::Context ctx;
  std::vector<std::pair<DcaePoint, int>> seen;
  auto obs = [&](DcaePoint p, int s, std::int64_t image, const HostTensor& t) {
    CHECK(t.size(0) == 1);
    if (image == 0) seen.emplace_back(p, s);
  };
  const HostTensor z = random_latents(1, 3);
  const HostTensor image = shared_dcae().decode(ctx, z, false, obs);
  const HostTensor back = shared_dcae().encode(ctx, image, obs);
  using P = DcaePoint;
  const std::vector<std::pair<DcaePoint, int>> expected = {
      {P::DecoderTemporal, 0}, {P::DecoderProjectIn, 0}, {P::DecoderStage, 5}, {P::DecoderStage, 4},
      {P::DecoderStage, 3},    {P::DecoderStage, 2},     {P::DecoderStage, 1}, {P::DecoderImage, 0},
      {P::EncoderProjectIn, 0}, {P::EncoderStage, 1},    {P::EncoderStage, 2}, {P::EncoderStage, 3},
      {P::EncoderStage, 4},    {P::EncoderStage, 5},     {P::EncoderLatent, 0}};
  CHECK(seen == expected);
  CHECK(back.shape() == z.shape());
}

TEST_CASE("bf16 weights: same model, bf16-level error against the float32 weights") {
  cpu::Context ctx;
  const auto m16 = Dcae<Cpu, bf16>::load(weights(), config());
  const HostTensor z = random_latents(1, 5);
  const double decode_rel = rel_max(m16.decode(ctx, z, false), shared_dcae().decode(ctx, z, false));
  const HostTensor image = shared_dcae().decode(ctx, z, false);
  const double encode_rel = rel_max(m16.encode(ctx, image), shared_dcae().encode(ctx, image));
  MESSAGE("bf16 weights vs fp32 weights: decode rel_max " << decode_rel << ", encode rel_max " << encode_rel);
  CHECK(decode_rel > 0);
  CHECK(decode_rel < 5e-2);
  CHECK(encode_rel < 5e-2);
}

TEST_CASE("bad inputs are refused with the problem named") {
  cpu::Context ctx;
  const std::int64_t Tc = config().condition_frames;
  CHECK_THROWS_WITH_AS(shared_dcae().decode(ctx, random_latents(Tc + 1, 1), true),
                       doctest::Contains("not whole clips of condition_frames"), Error);
  CHECK_THROWS_WITH_AS(shared_dcae().decode(ctx, HostTensor::zeros({1, 3, 2, 2}), false), doctest::Contains("latents must be"),
                       Error);
  CHECK_THROWS_WITH_AS(shared_dcae().encode(ctx, HostTensor::zeros({1, 3, 48, 64})), doctest::Contains("not a multiple of 32"),
                       Error);
  CHECK_THROWS_WITH_AS(shared_dcae().encode(ctx, HostTensor::zeros({1, 4, 64, 64})), doctest::Contains("images must be"),
                       Error);
  DcaeConfig broken = config();
  broken.encoder_width_list[5] = 33;
  CHECK_THROWS_AS(Model{broken}, Error);
}

TEST_CASE("FLOP count of the real f32c32 at 512x1024 matches spec §12 (torch flop_counter)") {
  const DcaeConfig real;  // defaults = Epona's nuPlan DC-AE
  const DcaeFlops f = dcae_flops(real, 512, 1024);
  MESSAGE("encode " << f.encode / 1e9 << " GFLOP, decode " << f.decode / 1e9 << " + temporal " << f.temporal / 1e9
                    << " GFLOP per frame");
  CHECK(f.encode / 1e9 == doctest::Approx(4170.9).epsilon(1e-4));
  CHECK(f.decode_total() / 1e9 == doctest::Approx(5539.4).epsilon(1e-4));
  CHECK(f.temporal / 1e9 == doctest::Approx(0.46).epsilon(2e-2));
  CHECK(6 * dcae_flops(real, 512, 1024, 6).decode_total() / 1e9 == doctest::Approx(33236.4).epsilon(1e-4));
}
