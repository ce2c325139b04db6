// Every header of include/epona in two translation units of one program (this file and
// header_units/second_unit.cu, both including the list CMake writes, every_header.hpp): a header-only
// library must link when a user's program includes it from several files. A plain `__global__`
// kernel or a non-inline function in a header is defined once per unit, and the link fails; this
// program then does not build (the check CI runs without a GPU). On a GPU each unit launches the
// headers' marker kernels (templates, compiled into both units) and must get the answers the
// kernels' dispatch uses (sm_90a code present, clusters).
#include <doctest/doctest.h>

#include "cuda_test_util.cuh"
#include "every_header.hpp"

namespace epona::test {
bool second_unit_has_sm90a();
bool second_unit_has_clusters();
}  // namespace epona::test

using namespace epona;

TEST_CASE("every header in two units: one program, and both units see the same build") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const bool hopper = ctx.info().major == 9 && ctx.info().minor == 0;
  const bool sm90a = cuda::detail::build_marked(cuda::detail::wgmma_marker_kernel<>);
  const bool clusters = cuda::detail::build_marked(cuda::detail::cluster_marker_kernel<>);
  CHECK(test::second_unit_has_sm90a() == sm90a);
  CHECK(test::second_unit_has_clusters() == clusters);
  CHECK(cuda::detail::sm90a_available(ctx) == (hopper && sm90a));
  CHECK(cuda::detail::clusters_available(ctx) == (ctx.info().major >= 9 && clusters));
  MESSAGE("sm_90a code: ", sm90a, ", clusters: ", clusters);
}
