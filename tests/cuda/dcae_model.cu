// The whole DC-AE on the GPU (model/dcae.hpp instantiated on Cuda): every `dcae.*` case of the
// golden set (EPONA_GOLDEN_DIR) in float32 with rel_max = max|ours - golden| / max|golden| <= 1e-4
// with each convolution engine; in bf16 within twice the official bf16-autocast error of each
// tensor (manifest.json "dcae_bf16_autocast_vs_fp32_golden"); and GPU vs CPU on random weights
// at a size whose deep stages take LiteMLA's quadratic order. Every buffer the model allocates
// on the GPU is poisoned (NaN) when handed out, so unwritten elements fail the checks.
#include <nlohmann/json.hpp>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "dcae_testing.cuh"
#include "../metrics.hpp"
#include "epona/cuda/backend.cuh"
#include "epona/domain/config_json.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/model/dcae.hpp"
#include "../golden_dir.hpp"

using namespace epona;
using epona::test::golden_dir;
using namespace epona::test;

namespace {

struct Golden {
  io::TensorMap weights = io::load_safetensors(golden_dir() + "/weights_dcae.safetensors");
  io::TensorMap cases = io::load_safetensors(golden_dir() + "/cases.safetensors");
  DcaeConfig config = io::load_configs(golden_dir() + "/configs.json").dcae;
  nlohmann::json manifest = nlohmann::json::parse(std::ifstream(golden_dir() + "/manifest.json"));
  HostF tensor(const std::string& name) const { return io::to_tensor<float>(cases.at(name)); }
  // The official recipe's DC-AE under bf16 autocast vs the float32 golden values.
  double bf16_autocast_rel_max(const std::string& name) const {
    return manifest.at("tolerance_official_bf16_recipe")
        .at("dcae_bf16_autocast_vs_fp32_golden")
        .at(name)
        .at("rel_max")
        .get<double>();
  }
};

const Golden& golden() {
  static const Golden g;
  return g;
}

std::string golden_name(const std::string& side, DcaePoint p, int stage) {
  switch (p) {
    case DcaePoint::DecoderTemporal: return side + ".temporal_out";
    case DcaePoint::DecoderProjectIn: return side + ".project_in_out";
    case DcaePoint::DecoderStage:
    case DcaePoint::EncoderStage: return side + ".stage" + std::to_string(stage) + "_out";
    default: return "";
  }
}

// Runs decode / encode / clip decode of the golden set on the GPU with weights T and hands
// every golden-named result (host NCHW float) to `check(name, tensor)`.
template <class T, class Check>
void run_golden(Check check) {
  PoisonBuffers poisoned;
  cuda::Context& ctx = gpu();
  const auto model = Dcae<Cuda, T>::load(golden().weights, golden().config);
  std::map<std::string, HostF> seen;
  const auto observer = [&](const std::string& side) {
    return DcaeObserver<Cuda>([&, side](DcaePoint p, int stage, std::int64_t image, const Dev<float>& t) {
      const std::string name = golden_name(side, p, stage);
      if (name.empty() || !golden().cases.contains(name)) return;
      const HostF ref = golden().tensor(name);
      if (!seen.count(name)) seen.emplace(name, HostF::zeros(ref.shape()));
      HostF slot = seen.at(name).slice(image, image + 1);
      REQUIRE(slot.shape() == t.shape());
      const HostF got = download(ctx, t);
      std::copy_n(got.data(), got.numel(), slot.data());
    });
  };
  const HostF image = download(ctx, model.decode(ctx, upload<float>(ctx, golden().tensor("dcae.decode.latent_in")), false,
                                                 observer("dcae.decode")));
  check("dcae.image", image);
  const HostF latent =
      download(ctx, model.encode(ctx, upload<float>(ctx, golden().tensor("dcae.image")), observer("dcae.encode")));
  check("dcae.encode.latent_out", latent);
  const HostF clip = golden().tensor("dcae.clip.latent_in");
  const HostF images = download(ctx, model.decode(ctx, upload<float>(ctx, clip), true, observer("dcae.clip")));
  CHECK(images.size(0) == clip.size(0));
  for (const auto& [name, t] : seen) check(name, t);
}

}  // namespace

TEST_CASE("DC-AE on the GPU, float32: every dcae.* golden case within 1e-4, with each conv engine") {
  EPONA_REQUIRE_GPU();
  std::vector<cuda::ConvEngine> engines{cuda::ConvEngine::Auto};  // float32 Auto: cuBLASLt
  if (cuda::cudnn_unavailable(gpu()).empty()) engines.push_back(cuda::ConvEngine::Cudnn);
  for (const auto engine : engines) {
    UseEngine use(engine);
    std::printf("DC-AE golden set %s, float32 on the GPU, conv engine %s\n", golden_dir().c_str(), engine_name(engine));
    std::set<std::string> checked;
    run_golden<float>([&](const std::string& name, const HostF& ours) {
      INFO("golden tensor " << name);
      const HostF ref = golden().tensor(name);
      REQUIRE(ours.shape() == ref.shape());
      const double rel = rel_max(ours, ref);
      std::printf("  %-30s %-18s rel_max = %.3e\n", name.c_str(), shape_str(ref.shape()).c_str(), rel);
      CHECK(rel <= 1e-4);
      checked.insert(name);
    });
    for (const auto& name : golden().cases.names()) {
      if (name.rfind("dcae.", 0) != 0 || name.size() < 3 || name.compare(name.size() - 3, 3, "_in") == 0) continue;
      CHECK_MESSAGE(checked.count(name), "golden output '" << name << "' was not compared");
    }
  }
}

TEST_CASE("DC-AE on the GPU, bf16: every dcae.* golden case within twice the official bf16 autocast error") {
  EPONA_REQUIRE_GPU();
  std::printf("DC-AE golden set, bf16 weights and activations on the GPU\n");
  int compared = 0;
  run_golden<bf16>([&](const std::string& name, const HostF& ours) {
    INFO("golden tensor " << name);
    const HostF ref = golden().tensor(name);
    REQUIRE(ours.shape() == ref.shape());
    const double rel = rel_max(ours, ref), bound = 2 * golden().bf16_autocast_rel_max(name);
    std::printf("  %-30s rel_max = %.3e  (official bf16 autocast %.3e, bound %.3e)\n", name.c_str(), rel, bound / 2,
                bound);
    CHECK(rel <= bound);
    ++compared;
  });
  CHECK(compared >= 10);
}

TEST_CASE("DC-AE on the GPU vs the CPU, random weights, 64x96 (quadratic LiteMLA in stages 4-5), float32") {
  EPONA_REQUIRE_GPU();
  PoisonBuffers poisoned;
  DcaeConfig c = golden().config;
  c.image_h = 64, c.image_w = 96, c.condition_frames = 2;
  Dcae<Cpu, float> cpu_model(c);
  Dcae<Cuda, float> gpu_model(c);
  cpu_model.randomize(7);
  gpu_model.randomize(7);
  const HostF images = random_tensor({2, 3, 64, 96}, 11);
  const HostF latents = random_tensor({2, 32, 2, 3}, 12, -2.f, 2.f);
  cuda::Context& ctx = gpu();
  const auto compare = [](const char* what, const HostF& out, const HostF& ref) {
    check_error(measure(out, ref), {kF32Tol, 1e-4 * max_abs(ref)}, what);
  };
  // Three calls of each with new inputs: the first runs eagerly, the second records the pass as
  // a CUDA graph, the third replays it (inputs staged into the buffer the graph reads).
  for (int call = 0; call < 3; ++call) {
    const std::string n = " (call " + std::to_string(call + 1) + ")";
    const HostF images = random_tensor({2, 3, 64, 96}, 11 + call);
    const HostF latents = random_tensor({2, 32, 2, 3}, 21 + call, -2.f, 2.f);
    compare(("encode 2 images" + n).c_str(), download(ctx, gpu_model.encode(ctx, upload<float>(ctx, images))),
            cpu_model.encode(host(), images));
    compare(("decode 2 single frames" + n).c_str(),
            download(ctx, gpu_model.decode(ctx, upload<float>(ctx, latents), false)),
            cpu_model.decode(host(), latents, false));
    compare(("decode a clip of 2" + n).c_str(), download(ctx, gpu_model.decode(ctx, upload<float>(ctx, latents), true)),
            cpu_model.decode(host(), latents, true));
  }
  gpu_model.use_graphs = false;
  compare("decode 2 single frames, graphs off", download(ctx, gpu_model.decode(ctx, upload<float>(ctx, latents), false)),
          cpu_model.decode(host(), latents, false));
  CHECK_THROWS_WITH_AS(gpu_model.decode(ctx, upload<float>(ctx, images), false),
                       doctest::Contains("latents must be (N, 32, h, w)"), Error);
}

TEST_CASE("DC-AE on the GPU, bf16, replayed graph: equal to the eager pass bit for bit") {
  EPONA_REQUIRE_GPU();
  DcaeConfig c = golden().config;
  Dcae<Cuda, bf16> model(c);
  model.randomize(3);
  cuda::Context& ctx = gpu();
  const Dev<float> latents = upload<float>(ctx, random_tensor({1, 32, 4, 9}, 31, -2.f, 2.f));
  model.use_graphs = false;
  const HostF eager = download(ctx, model.decode(ctx, latents, false));
  model.use_graphs = true;
  HostF replayed;
  for (int call = 0; call < 3; ++call) replayed = download(ctx, model.decode(ctx, latents, false));
  const Diff e = measure(replayed, eager);
  CHECK(e.nans == 0);
  CHECK(e.max_abs == 0);
}

TEST_CASE("cuDNN state released before exit (and made again on demand)") {
  EPONA_REQUIRE_GPU();
  cuda::release_cudnn();
  CHECK(cuda::cudnn_unavailable(gpu()) == cuda::cudnn_unavailable(gpu()));  // a handle is made again, same verdict
  cuda::release_cudnn();
}
