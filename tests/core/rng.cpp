// Tests for epona/core/rng.hpp: bit-exact agreement with real PyTorch (reference vectors made
// by scripts/make_rng_vectors.py with torch 1.13, both CPU kernels), including multi-draw
// sequences from one generator, plus the well-known seed-0 values.
#include <doctest/doctest.h>

#include <cstring>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "epona/core/rng.hpp"

using namespace epona;
using nlohmann::json;

namespace {

json load_vectors(const std::string& name) {
  const std::string path = std::string(EPONA_TEST_DATA_DIR) + "/rng/" + name;
  std::ifstream in(path);
  REQUIRE_MESSAGE(in, "cannot open " << path << " (make it with scripts/make_rng_vectors.py)");
  return json::parse(in);
}

std::uint32_t bits(float f) {
  std::uint32_t u;
  std::memcpy(&u, &f, 4);
  return u;
}

// Replays every case of a reference file; returns the number of elements compared.
std::size_t check_file(const std::string& name, RandnKernel kernel) {
  const json ref = load_vectors(name);
  std::size_t compared = 0;
  for (const auto& c : ref.at("cases")) {
    TorchGenerator gen(c.at("seed").get<std::uint64_t>(), kernel);
    int draw_index = 0;
    for (const auto& d : c.at("draws")) {
      const Shape shape = d.at("shape").get<Shape>();
      const auto expected = d.at("bits").get<std::vector<std::uint32_t>>();
      const Tensor<float> t = gen.randn(shape);
      REQUIRE(t.numel() == std::int64_t(expected.size()));
      std::size_t mismatches = 0, first = 0;
      for (std::size_t i = 0; i < expected.size(); ++i)
        if (bits(t.data()[i]) != expected[i] && mismatches++ == 0) first = i;
      INFO(name << " seed " << c.at("seed") << " draw " << draw_index << " shape " << shape_str(shape));
      CHECK_MESSAGE(mismatches == 0, mismatches << " mismatching elements, first at " << first);
      compared += expected.size();
      ++draw_index;
    }
  }
  return compared;
}

}  // namespace

TEST_CASE("randn equals PyTorch bit for bit: AVX2 kernel") {
  CHECK(check_file("randn_avx2.json", RandnKernel::Avx2) > 10000);
}

TEST_CASE("randn equals PyTorch bit for bit: generic kernel") {
  CHECK(check_file("randn_generic.json", RandnKernel::Generic) > 10000);
}

TEST_CASE("normal_double equals float64 torch.randn bit for bit (the path below 16 floats)") {
  const json ref = load_vectors("randn_avx2.json");
  std::size_t compared = 0;
  for (const auto& c : ref.at("normal_double")) {
    TorchGenerator gen(c.at("seed").get<std::uint64_t>());
    std::size_t mismatches = 0;
    for (const auto& hex : c.at("hex")) {
      const double v = gen.normal_double();
      std::uint64_t u;
      std::memcpy(&u, &v, 8);
      mismatches += u != std::stoull(hex.get<std::string>(), nullptr, 16);
      ++compared;
    }
    CHECK_MESSAGE(mismatches == 0, "seed " << c.at("seed") << ": " << mismatches << " mismatches");
  }
  CHECK(compared > 1000);
}

TEST_CASE("the well-known seed-0 values") {
  TorchGenerator gen(0);
  const auto a = gen.randn({8});
  const float a_ref[] = {1.5410f, -0.2934f, -2.1788f, 0.5684f};
  for (int i = 0; i < 4; ++i) CHECK(a.at(i) == doctest::Approx(a_ref[i]).epsilon(1e-4));

  gen.manual_seed(0);
  const auto b = gen.randn({20});
  const float head[] = {-1.1258f, -1.1524f, -0.2506f, -0.4339f};
  const float tail[] = {0.9318f, 1.2590f, 2.0050f, 0.0537f};
  for (int i = 0; i < 4; ++i) {
    CHECK(b.at(i) == doctest::Approx(head[i]).epsilon(1e-4));
    CHECK(b.at(16 + i) == doctest::Approx(tail[i]).epsilon(1e-4));
  }
}

TEST_CASE("generator state: seeding resets the cached normal, randn_into equals randn") {
  TorchGenerator gen(5);
  const float first = gen.randn({1}).at(0);
  const float second = gen.randn({1}).at(0);  // the cached sine branch
  CHECK(first != second);
  gen.manual_seed(5);
  CHECK(bits(gen.randn({1}).at(0)) == bits(first));

  TorchGenerator g1(77), g2(77);
  std::vector<float> buf(123);
  g1.randn_into(buf.data(), 123);
  const auto t = g2.randn({3, 41});
  for (int i = 0; i < 123; ++i) CHECK(bits(buf[std::size_t(i)]) == bits(t.data()[i]));
  // Seeds use the low 32 bits, like torch.manual_seed.
  TorchGenerator lo(5), hi((std::uint64_t{1} << 32) + 5);
  CHECK(bits(lo.randn({20}).at(19)) == bits(hi.randn({20}).at(19)));
  // Empty draws take nothing from the generator.
  TorchGenerator e1(9), e2(9);
  CHECK(e1.randn({0, 4}).numel() == 0);
  CHECK(bits(e1.randn({3}).at(2)) == bits(e2.randn({3}).at(2)));
  CHECK_THROWS_AS(gen.randn_into(buf.data(), -1), Error);
}
