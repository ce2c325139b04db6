// The umbrella header compiles on its own and exposes the public API (no CUDA, no stb TU).
#include <epona/epona.hpp>

#include <doctest/doctest.h>

TEST_CASE("epona/epona.hpp exposes the configuration, readers and models") {
  epona::WorldModelConfig world;
  CHECK_NOTHROW(world.validate());
  CHECK(world.img_tokens() == 512);
  epona::DcaeConfig dcae;
  CHECK_NOTHROW(dcae.validate());
  CHECK_THROWS_AS(epona::io::load_weights("/nonexistent/weights.safetensors"), epona::Error);
}
