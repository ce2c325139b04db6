// epona/io/stb_implementation.hpp — compiles stb_image and stb_image_write (PNG/JPEG decoding,
// PNG encoding for epona/io/image.hpp). Include this in EXACTLY ONE translation unit of a
// program, or link a compiled stb instead (Debian: -lstb) and never include it.
// No other epona header defines the STB_*_IMPLEMENTATION macros.
#pragma once

#if defined(STB_IMAGE_IMPLEMENTATION) || defined(STB_IMAGE_WRITE_IMPLEMENTATION)
#error "epona/io/stb_implementation.hpp: the stb implementation macros are already defined in this translation unit"
#endif

#define STB_IMAGE_IMPLEMENTATION
#define STB_IMAGE_WRITE_IMPLEMENTATION
#define STBI_ONLY_PNG
#define STBI_ONLY_JPEG

#if defined(__GNUC__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
#pragma GCC diagnostic ignored "-Wunused-function"
#pragma GCC diagnostic ignored "-Wsign-compare"
#pragma GCC diagnostic ignored "-Wunused-but-set-variable"
#endif

#if __has_include(<stb/stb_image.h>)
#include <stb/stb_image.h>
#include <stb/stb_image_write.h>
#else
#include <stb_image.h>
#include <stb_image_write.h>
#endif

#if defined(__GNUC__)
#pragma GCC diagnostic pop
#endif

// Later inclusions of the stb headers must not compile the implementation again.
#undef STB_IMAGE_IMPLEMENTATION
#undef STB_IMAGE_WRITE_IMPLEMENTATION
