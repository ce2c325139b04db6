// epona/cuda/runtime/cluster.cuh — thread-block clusters (sm_90 on): whether this build and GPU have
// them, a cluster-wide barrier, and a launch in clusters. Kernels whose CTAs share partial
// results through distributed shared memory (skinny_linear.cuh, short_attention_qk_layer_norm.cuh) use these.
#pragma once

#include <cuda_runtime.h>

#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"

// Device code built for targets before sm_90 leaves the cluster parts out (the host never
// launches a cluster kernel there: clusters_available).
#if !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 900
#define EPONA_CUDA_CLUSTERS 1
#else
#define EPONA_CUDA_CLUSTERS 0
#endif

namespace epona::cuda::detail {

// Both halves of a cluster-wide barrier (the sm_90 runtime intrinsics: cooperative_groups.h
// would bring a namespace `cuda` that clashes with epona::cuda under `using namespace epona`).
// The halves apart let a CTA work between its last read of another CTA's shared memory
// (arrive) and its exit (wait: no CTA frees its shared memory while another may still read it).
__device__ __forceinline__ void cluster_arrive() {
#if EPONA_CUDA_CLUSTERS
  __cluster_barrier_arrive();
#endif
}
__device__ __forceinline__ void cluster_wait() {
#if EPONA_CUDA_CLUSTERS
  __cluster_barrier_wait();
#endif
}
__device__ __forceinline__ void cluster_sync() {
  cluster_arrive();
  cluster_wait();
}

// The same shared-memory object in the cluster's CTA `rank` (distributed shared memory).
template <class T>
__device__ __forceinline__ const T* cluster_peer(T* local, int rank) {
#if EPONA_CUDA_CLUSTERS
  return static_cast<const T*>(__cluster_map_shared_rank(local, static_cast<unsigned>(rank)));
#else
  (void)rank;
  __trap();  // unreachable: no cluster launch on a pre-sm_90 build
  return local;
#endif
}

// Marks device code with clusters (mark_build).
// A template so that several translation units of one program can include it (docs/cuda.md).
template <int = 0>
__global__ void cluster_marker_kernel(int* flag) {
#if EPONA_CUDA_CLUSTERS
  mark_build(flag);
#else
  (void)flag;
#endif
}
// A GPU with clusters (compute capability 9.0 or newer) running code built with them.
inline bool clusters_available(const Context& ctx) {
  if (ctx.info().major < 9) return false;
  static const bool built = build_marked(cluster_marker_kernel<>);
  return built;
}

// Kernel launched on grid (x, y) in clusters of (cluster_x, 1, 1) with `smem` bytes of dynamic
// shared memory, as a programmatic dependent launch where on (launch_after: the kernel begins
// with wait_for_producer).
template <class... Params, class... Args>
void launch_in_clusters(void (*kernel)(Params...), dim3 grid, unsigned cluster_x, int threads, int smem,
                        const Context& ctx, Args... args) {
  cudaLaunchConfig_t cfg{};
  cfg.gridDim = grid;
  cfg.blockDim = dim3(static_cast<unsigned>(threads));
  cfg.dynamicSmemBytes = static_cast<std::size_t>(smem);
  cfg.stream = ctx.stream();
  cudaLaunchAttribute cluster{};
  cluster.id = cudaLaunchAttributeClusterDimension;
  cluster.val.clusterDim.x = cluster_x, cluster.val.clusterDim.y = 1, cluster.val.clusterDim.z = 1;
  cfg.attrs = &cluster;
  cfg.numAttrs = 1;
  launch_programmatic(cfg, ctx.policy().programmatic_launch, kernel, args...);
}

}  // namespace epona::cuda::detail
