// Parity of epona/model/dcae.hpp with the official DCAE on every `dcae.*` golden case: the set's
// weights (weights_dcae.safetensors) and config (configs.json "dcae"), single-frame decode with
// every intermediate the set stores, encode of the stored image, and a clip decode with causal
// time attention. rel = max|ours - golden| / max|golden| <= 1e-4 per tensor (README of the set);
// NaN fails. Every `dcae.*` output of the file must be checked here (none skipped silently).
#include <doctest/doctest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <set>
#include <string>

#include "../metrics.hpp"
#include "../cpu_context.hpp"
#include "epona/cpu/context.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/model/dcae.hpp"
#include "../golden_dir.hpp"

using namespace epona;
using epona::test::cpu_context;
using epona::test::golden_dir;
using epona::test::rel_max;
using HostTensor = Tensor<float, Cpu>;

namespace {

constexpr double kParityTolerance = 1e-4;

// $EPONA_DCAE_WEIGHTS (.safetensors or official-format .pkl) overrides the golden weights file.
std::string dcae_weights_path() {
  const char* env = std::getenv("EPONA_DCAE_WEIGHTS");
  return env && *env ? env : golden_dir() + "/weights_dcae.safetensors";
}

struct Golden {
  io::TensorMap weights = io::load_weights(dcae_weights_path());
  io::TensorMap cases = io::load_safetensors(golden_dir() + "/cases.safetensors");
  DcaeConfig config = io::load_configs(golden_dir() + "/configs.json").dcae;
  HostTensor input(const std::string& name) const { return io::to_tensor<float>(cases.at(name)); }
};

const Golden& golden() {
  static const Golden g;
  return g;
}

const Dcae<Cpu, float>& golden_dcae() {
  static const Dcae<Cpu, float> m = Dcae<Cpu, float>::load(golden().weights, golden().config);
  return m;
}

// Names checked so far; the last test case verifies that every dcae.* output is among them.
std::set<std::string>& checked() {
  static std::set<std::string> s;
  return s;
}

void compare(const std::string& name, const HostTensor& ours) {
  INFO("golden tensor " << name);
  REQUIRE_MESSAGE(golden().cases.contains(name), "golden set has no '" << name << "'");
  const HostTensor ref = golden().input(name);
  REQUIRE_MESSAGE(ours.shape() == ref.shape(),
                  "shape " << shape_str(ours.shape()) << " vs golden " << shape_str(ref.shape()));
  const double rel = rel_max(ours, ref);
  std::printf("  %-30s %-18s rel_max = %.3e\n", name.c_str(), shape_str(ref.shape()).c_str(), rel);
  CHECK_MESSAGE(rel <= kParityTolerance, name << ": rel_max " << rel << " > " << kParityTolerance);
  checked().insert(name);
}

// Collects an observer's tensors by golden name (batch index `image` along dimension 0).
struct Recorder {
  std::map<std::string, HostTensor> seen;
  std::map<std::string, std::int64_t> batch;

  DcaeObserver<Cpu> observer(const std::string& side) {
    return [this, side](DcaePoint p, int stage, std::int64_t image, const HostTensor& t) {
      const std::string name = golden_name(side, p, stage);
      if (name.empty() || !golden().cases.contains(name)) return;
      const HostTensor ref = golden().input(name);
      if (!seen.count(name)) seen.emplace(name, HostTensor::zeros(ref.shape()));
      HostTensor dst = seen.at(name);
      REQUIRE_MESSAGE(image < dst.size(0), name << ": image " << image << " beyond golden batch");
      HostTensor slot = dst.slice(image, image + 1);
      REQUIRE_MESSAGE(slot.shape() == t.shape(), name << ": observed " << shape_str(t.shape()) << " vs golden slice "
                                                      << shape_str(slot.shape()));
      std::copy_n(t.data(), t.numel(), slot.data());
    };
  }
  static std::string golden_name(const std::string& side, DcaePoint p, int stage) {
    switch (p) {
      case DcaePoint::DecoderTemporal: return side + ".temporal_out";
      case DcaePoint::DecoderProjectIn: return side + ".project_in_out";
      case DcaePoint::DecoderStage:
      case DcaePoint::EncoderStage: return side + ".stage" + std::to_string(stage) + "_out";
      default: return "";
    }
  }
  void compare_all() {
    for (auto& [name, t] : seen) compare(name, t);
  }
};

}  // namespace

TEST_CASE("dcae parity: config and weights bind strictly") {
  std::printf("DC-AE golden set %s\n", golden_dir().c_str());
  const auto& c = golden().config;
  std::printf("  image %lldx%lld, widths [%lld..%lld], clip %lld frames\n", (long long)c.image_h,
              (long long)c.image_w, (long long)c.encoder_width_list.front(), (long long)c.encoder_width_list.back(),
              (long long)c.condition_frames);
  CHECK_NOTHROW(golden_dcae());
}

TEST_CASE("dcae parity: single-frame decode (is_video = false) with its intermediates") {
  Recorder rec;
  const HostTensor latent = golden().input("dcae.decode.latent_in");
  const HostTensor image = golden_dcae().decode(cpu_context(), latent, false, rec.observer("dcae.decode"));
  rec.compare_all();
  compare("dcae.image", image);
}

TEST_CASE("dcae parity: encode of the stored image with its intermediates") {
  Recorder rec;
  const HostTensor image = golden().input("dcae.image");
  const HostTensor latent = golden_dcae().encode(cpu_context(), image, rec.observer("dcae.encode"));
  rec.compare_all();
  compare("dcae.encode.latent_out", latent);
}

TEST_CASE("dcae parity: clip decode (is_video = true) through the causal temporal blocks") {
  Recorder rec;
  const HostTensor clip = golden().input("dcae.clip.latent_in");
  REQUIRE(clip.size(0) % golden().config.condition_frames == 0);
  const HostTensor images = golden_dcae().decode(cpu_context(), clip, true, rec.observer("dcae.clip"));
  CHECK(images.size(0) == clip.size(0));
  rec.compare_all();
}

TEST_CASE("dcae parity: every dcae.* output of the golden set was checked") {
  const auto is_input = [](const std::string& n) { return n.size() >= 3 && n.compare(n.size() - 3, 3, "_in") == 0; };
  for (const auto& name : golden().cases.names()) {
    if (name.rfind("dcae.", 0) != 0 || is_input(name)) continue;
    CHECK_MESSAGE(checked().count(name), "golden output '" << name << "' was not compared");
  }
}
