// fuzz/fuzz_image.cpp — decode_image (PNG/JPEG container checks, stb decoding, channel and depth
// policy, size policies with PIL-bicubic resizing and cropping) on arbitrary bytes. The first byte
// picks the options: bit 0 convert_to_rgb8; bits 1-2 the SizePolicy; bit 3 a target size (else
// the file's own), bit 4 making it 64x32 instead of 32x32. The rest is the image file. An accepted
// image must have the requested size and convert to the model's (1, 3, H, W) tensor.
#include "epona/io/image.hpp"
#include "epona/io/stb_implementation.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(image) {
  if (size == 0) return 0;
  epona::io::ImageReadOptions opt;
  opt.convert_to_rgb8 = data[0] & 1;
  opt.size = static_cast<epona::io::SizePolicy>((data[0] >> 1) & 3);
  if (data[0] & 8) opt.height = 32, opt.width = data[0] & 16 ? 64 : 32;
  return epona_fuzz::run([&] {
    const auto img = epona::io::decode_image({data + 1, size - 1}, "fuzz.img", opt);
    epona_fuzz::require(opt.height == 0 || (img.height == opt.height && img.width == opt.width),
                        "an accepted image has the requested size");
    epona_fuzz::require(img.rgb.size() == static_cast<std::size_t>(img.height * img.width * 3),
                        "an image holds height x width RGB pixels");
    epona_fuzz::require(epona::io::image_to_tensor(img).numel() == img.height * img.width * 3,
                        "the model tensor has one value per sample");
  });
}
