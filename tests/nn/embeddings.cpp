// The two sinusoidal embeddings against float64 loops: Fourier ([sin | cos], frequencies
// 100^(k/256)) and timestep ([cos | sin], t·1000, frequencies exp(-ln(1e4)·k/128)). The
// difference is the fp32 rounding of the official arguments, |a|·2^-23 at most, so the bound is
// stated relative to the largest argument; the block order is checked exactly.
#include <doctest/doctest.h>

#include <cmath>

#include "epona/nn/embeddings.hpp"
#include "world_reference.hpp"

using namespace epona;
using world_ref::i64;

namespace {
double max_abs(const std::vector<float>& a, const world_ref::Vec& b) {
  double e = 0;
  for (std::size_t i = 0; i < b.size(); ++i) e = std::max(e, std::abs(a[i] - b[i]));
  return e;
}
}  // namespace

TEST_CASE("Fourier embedding: sin block, then cos block") {
  const world_ref::Vec coords{0.0, 0.03125, 0.5, 0.99609375, 1.0, 0.123456};
  for (const i64 dim : {512, 8}) {
    std::vector<float> in(coords.begin(), coords.end()), out(coords.size() * dim);
    nn::fourier_embed(in.data(), i64(in.size()), dim, 100.0f, out.data());
    const double err = max_abs(out, world_ref::fourier(coords, dim, 100.0));
    MESSAGE("Fourier dim ", dim, ": max |error| ", err, " (largest argument 100 rad)");
    CHECK(err <= 100 * 3 * 0x1p-23);
    CHECK(out[0] == 0.0f);        // sin(0)
    CHECK(out[dim / 2] == 1.0f);  // cos(0)
  }
}

TEST_CASE("timestep embedding: cos block, then sin block; odd widths padded with a zero") {
  const world_ref::Vec ts{0.0, 0.0058324933, 0.25, 0.731, 0.98290598, 1.0};
  for (const i64 dim : {256, 7}) {
    std::vector<float> in(ts.begin(), ts.end()), out(ts.size() * dim);
    nn::timestep_embedding(in.data(), i64(in.size()), dim, 10000.0, 1000.0f, out.data());
    world_ref::Vec ref;
    for (double t : ts) {
      const auto row = world_ref::timestep(double(float(t)), dim, 10000.0, 1000.0);
      ref.insert(ref.end(), row.begin(), row.end());
    }
    const double err = max_abs(out, ref);
    MESSAGE("timestep dim ", dim, ": max |error| ", err, " (largest argument 1000 rad)");
    CHECK(err <= 1000 * 3 * 0x1p-23);
    CHECK(out[0] == 1.0f);            // cos(0) first
    CHECK(out[dim / 2] == 0.0f);      // then sin(0)
    if (dim % 2) CHECK(out[dim - 1] == 0.0f);
  }
}

TEST_CASE("embedding widths are checked") {
  float c = 0, out[4];
  CHECK_THROWS_AS(nn::fourier_embed(&c, 1, 3, 100.f, out), Error);
  CHECK_THROWS_AS(nn::timestep_embedding(&c, 1, 1, 1e4, 1e3f, out), Error);
}
