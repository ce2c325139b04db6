// example_autoencode — the DC-AE f32c32 with Epona's temporal decoder, through the library API:
// encode images into latents (C, H/32, W/32), decode them back frame by frame and, when there
// are enough frames, as one temporal clip; save the reconstructions and print their PSNR.
//
// usage: example_autoencode [MODEL_DIR [IMAGE...]]     (run from the repository root)
//   MODEL_DIR  configs.json + weights_dcae.safetensors (default tests/data/golden: random
//              conformance weights, so the reconstructions are noise; the released
//              dcae_td_20000.pkl loads with io::load_weights and DcaeConfig{})
//   IMAGE      PNG/JPEG files of one size, multiples of 32 per side
//              (default: the frames of tests/data/demo); outputs go to out/example_autoencode
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "epona/cpu/context.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/image.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/model/dcae.hpp"

using namespace epona;

namespace {

double psnr(const io::Image& a, const io::Image& b) {
  double sum = 0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) sum += std::pow(double(a.rgb[i]) - double(b.rgb[i]), 2);
  const double mse = sum / double(a.rgb.size());
  return mse == 0 ? INFINITY : 10.0 * std::log10(255.0 * 255.0 / mse);
}

}  // namespace

int main(int argc, char** argv) {
  const std::string model_dir = argc > 1 ? argv[1] : "tests/data/golden";
  std::vector<std::string> paths(argv + std::min(argc, 2), argv + argc);
  if (paths.empty())
    for (int i = 0; i < 3; ++i) paths.push_back("tests/data/demo/frame_0" + std::to_string(i) + ".png");
  const std::filesystem::path out = "out/example_autoencode";
  try {
    const DcaeConfig cfg = io::load_configs(model_dir + "/configs.json").dcae;
    const auto dcae = Dcae<Cpu, float>::load(io::load_weights(model_dir + "/weights_dcae.safetensors"), cfg);
    std::vector<io::Image> images;
    for (const auto& p : paths) images.push_back(io::read_image(p));  // 8-bit RGB, sides multiples of 32

    cpu::Context ctx;
    const Tensor<float> latents = dcae.encode(ctx, io::images_to_tensor(images));  // (N, C, H/32, W/32)
    std::printf("encoded %zu image(s) of %lldx%lld into latents %s\n", images.size(),
                static_cast<long long>(images[0].height), static_cast<long long>(images[0].width),
                shape_str(latents.shape()).c_str());

    std::filesystem::create_directories(out);
    const Tensor<float> single = dcae.decode(ctx, latents, /*is_video=*/false);  // (N, 3, H, W)
    const std::int64_t clip = cfg.add_decoder_temporal ? cfg.condition_frames : 0;
    const bool as_clip = clip > 1 && latents.size(0) >= clip;
    const Tensor<float> video = as_clip ? dcae.decode(ctx, latents.slice(0, clip), /*is_video=*/true) : Tensor<float>();
    for (std::size_t i = 0; i < images.size(); ++i) {
      const auto n = static_cast<std::int64_t>(i);
      const io::Image frame = io::tensor_to_image(single, n);
      io::write_png((out / ("recon_" + std::to_string(i) + ".png")).string(), frame);
      std::printf("image %zu: PSNR %.2f dB decoded alone", i, psnr(images[i], frame));
      if (as_clip && n < clip) std::printf(", %.2f dB decoded in a %lld-frame clip", psnr(images[i], io::tensor_to_image(video, n)),
                                           static_cast<long long>(clip));
      std::printf("\n");
    }
    std::printf("wrote the reconstructions to %s/\n", out.string().c_str());
    return 0;
  } catch (const Error& e) {
    std::fprintf(stderr, "example_autoencode: error: %s\n", e.what());
    return 1;
  }
}

// stb is compiled in exactly one translation unit, after every other include.
#include "epona/io/stb_implementation.hpp"
