// The second translation unit of tests/cuda/header_units.cu: every header again.
#include "every_header.hpp"

namespace epona::test {
bool second_unit_has_sm90a() { return cuda::detail::build_marked(cuda::detail::wgmma_marker_kernel<>); }
bool second_unit_has_clusters() { return cuda::detail::build_marked(cuda::detail::cluster_marker_kernel<>); }
}  // namespace epona::test
