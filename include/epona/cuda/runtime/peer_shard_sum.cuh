// epona/cuda/runtime/peer_shard_sum.cuh — a tensor-parallel group over GPUs of one host that reach
// each other's memory (NVLink or PCIe peer access), whose ShardSum is one kernel of ours instead of
// an NCCL all-reduce: every rank writes its part straight into every other rank's inbox, raises a
// flag there, waits for theirs, and adds the parts in rank order (docs/parallel.md, "The peer
// group"). On two H200s NCCL's all-reduce of one block's output (4.2 MB) took 32.6 us alone and
// about 43 us inside the sampler; the part crosses NVLink once here, with no NCCL launch in
// between. The sums a graph records hold their group's fence, as NCCL's do (context.hpp), and
// every direct sum runs between two barriers of the ranks' threads, so a failed rank stops the
// others instead of leaving their kernels waiting for its flags.
//
// The protocol (kernel peer_sum_kernel): block b of every rank handles the same slice of the buffer
// and keeps a count of the sums it has run (its epoch e, in the rank's own memory, so a recorded
// graph's launches go on counting). It copies its slice into inbox slot e % 2 of every other rank,
// then raises flag[b][rank] = e on each (a release at system scope, after the copies), waits until
// its own flag[b][j] >= e for every other rank j (an acquire), and adds the parts in rank order in
// float32, rounded once to A: every rank gets the same bits. Two inbox slots are enough: a rank
// writes slot e % 2 again only at epoch e + 2, after every rank's block b has raised its flag for
// e + 1, which each does only after its whole epoch-e kernel (and its reading of that slot) ended.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <type_traits>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cuda/runtime/check.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/device.cuh"
#include "epona/cuda/runtime/device_shard_threads.hpp"
#include "epona/cuda/runtime/memory.hpp"

namespace epona::cuda {

struct PeerGroupOptions {
  // Elements of A one sum moves at a time: each rank holds two inbox slots of this many per rank
  // of the group (a larger sum goes in pieces of it). 4 Mi elements: a VisDiT block's output at
  // one item (1027 x 2048) in one piece, 32 MiB of bf16 inboxes per GPU of a pair.
  std::int64_t capacity = std::int64_t{1} << 22;
  // Blocks of the sum kernel; every rank uses the same (each block pairs with its namesakes). On two
  // H200s one sum of 4.2 MB took 36.2, 27.4, 22.8, 21.1 and 23.6 us at 16 to 256 blocks, and the
  // VisDiT's sample 194.1 ms at 64 and 190.8 ms at 128 (docs/parallel.md, "The peer group").
  int blocks = 128;
  // Several shards on one GPU (tests on a machine with one): their kernels must then run side by
  // side on it. A shard's sum holds its blocks' multiprocessors while it waits for the others, so
  // keep shards x blocks well under the GPU's multiprocessors, or the others' products never start.
  bool share_devices = false;
};

namespace detail {
inline constexpr int kMaxPeerShards = 8;
inline constexpr int kMaxPeerBlocks = 256;
inline constexpr int kPeerSumThreads = 512;

// What rank `rank` of a group needs to reach the others: every pointer into another GPU's memory is
// a peer mapping (cudaDeviceEnablePeerAccess).
struct PeerLinks {
  unsigned char* inbox_of[kMaxPeerShards];  // rank j's inbox (on GPU j): slot s, source r at (s * size + r) * capacity
  unsigned* flags_of[kMaxPeerShards];       // rank j's flags (on GPU j): [block][source rank]
  unsigned* epochs;                         // this rank's sums per block (on its GPU)
  int rank, size;
  std::int64_t capacity_bytes;
};

__device__ __forceinline__ void store_release_system(unsigned* p, unsigned v) {
  asm volatile("st.release.sys.global.u32 [%0], %1;" ::"l"(p), "r"(v) : "memory");
}
__device__ __forceinline__ unsigned load_acquire_system(const unsigned* p) {
  unsigned v;
  asm volatile("ld.acquire.sys.global.u32 %0, [%1];" : "=r"(v) : "l"(p) : "memory");
  return v;
}

// Loads that skip the SM's L1 (which peers' writes into this GPU's memory do not update): the
// inboxes are read this way.
// 16-byte words in a pack of 8 elements of A (one for bf16, two for float).
template <class A>
inline constexpr int kPackWords = static_cast<int>(sizeof(A)) * kPack / 16;

template <class A>
__device__ __forceinline__ void load8_from_l2(const A* p, float (&v)[kPack]) {
  alignas(16) A local[kPack];
#pragma unroll
  for (int w = 0; w < kPackWords<A>; ++w) reinterpret_cast<uint4*>(local)[w] = __ldcg(reinterpret_cast<const uint4*>(p) + w);
  load8(local, v);
}
__device__ __forceinline__ float load_from_l2(const float* p) { return __ldcg(p); }
__device__ __forceinline__ float load_from_l2(const bf16* p) {
  return __uint_as_float(static_cast<unsigned>(__ldcg(reinterpret_cast<const unsigned short*>(p))) << 16);
}

// The elements [begin, end) of block b of `blocks` over `count`, in whole packs of 8.
__device__ __forceinline__ void peer_slice(std::int64_t count, int b, int blocks, std::int64_t& begin,
                                           std::int64_t& end) {
  const std::int64_t per = (count + blocks - 1) / blocks, packed_per = (per + kPack - 1) / kPack * kPack;
  begin = std::min(count, b * packed_per);
  end = std::min(count, begin + packed_per);
}

template <class A>
__global__ void __launch_bounds__(kPeerSumThreads) peer_sum_kernel(PeerLinks links, A* data, std::int64_t count,
                                                                   bool packed) {
  __shared__ unsigned epoch_shared;
  const int b = blockIdx.x, me = links.rank;
  if (threadIdx.x == 0) epoch_shared = links.epochs[b] + 1;
  __syncthreads();
  const unsigned epoch = epoch_shared;
  const std::int64_t slot = epoch & 1u;
  std::int64_t begin = 0, end = 0;
  peer_slice(count, b, gridDim.x, begin, end);
  const auto inbox = [&](int owner, int source) {
    return reinterpret_cast<A*>(links.inbox_of[owner] + (slot * links.size + source) * links.capacity_bytes);
  };
  // 1. This slice of my part into every other rank's inbox.
  for (int j = 0; j < links.size; ++j) {
    if (j == me) continue;
    A* to = inbox(j, me);
    if (packed)
      for (std::int64_t c = begin + threadIdx.x * kPack; c < end; c += std::int64_t{blockDim.x} * kPack)
#pragma unroll
        for (int w = 0; w < kPackWords<A>; ++w)
          reinterpret_cast<uint4*>(to + c)[w] = reinterpret_cast<const uint4*>(data + c)[w];
    else
      for (std::int64_t c = begin + threadIdx.x; c < end; c += blockDim.x) to[c] = data[c];
  }
  // 2. Flags up once every thread's copies are out; then wait for the others' (epochs only grow:
  // another rank may already be one sum ahead).
  __syncthreads();
  if (threadIdx.x < links.size && static_cast<int>(threadIdx.x) != me) {
    __threadfence_system();
    store_release_system(links.flags_of[threadIdx.x] + b * kMaxPeerShards + me, epoch);
  }
  if (threadIdx.x < links.size && static_cast<int>(threadIdx.x) != me) {
    const unsigned* flag = links.flags_of[me] + b * kMaxPeerShards + threadIdx.x;
    while (static_cast<int>(load_acquire_system(flag) - epoch) < 0) {
    }
    __threadfence_system();
  }
  __syncthreads();
  // 3. The parts in rank order, in float32, rounded once.
  const auto part = [&](int j) -> const A* { return j == me ? data : inbox(me, j); };
  if (packed) {
    for (std::int64_t c = begin + threadIdx.x * kPack; c < end; c += std::int64_t{blockDim.x} * kPack) {
      float acc[kPack], v[kPack];
      load8_from_l2(part(0) + c, acc);
      for (int j = 1; j < links.size; ++j) {
        load8_from_l2(part(j) + c, v);
#pragma unroll
        for (int k = 0; k < kPack; ++k) acc[k] += v[k];
      }
      store8(data + c, acc);
    }
  } else {
    for (std::int64_t c = begin + threadIdx.x; c < end; c += blockDim.x) {
      float acc = load_from_l2(part(0) + c);
      for (int j = 1; j < links.size; ++j) acc += load_from_l2(part(j) + c);
      data[c] = from_f32<A>(acc);
    }
  }
  if (threadIdx.x == 0) links.epochs[b] = epoch;
}
// Lets GPU a reach GPU b's memory. The mapping lasts as long as the process, so each pair is
// mapped once, by every group of either activation type: mapping it again is an error CUDA reports
// (and compute-sanitizer lists), though harmless.
inline void map_peer_memory(int a, int b) {
  static std::once_flag mapped[kMaxDevices][kMaxDevices];
  std::call_once(mapped[a][b], [a, b] {
    EPONA_CUDA_CHECK(cudaSetDevice(a));
    const cudaError_t e = cudaDeviceEnablePeerAccess(b, 0);
    if (e == cudaErrorPeerAccessAlreadyEnabled)  // by another part of the program
      (void)cudaGetLastError();
    else
      EPONA_CUDA_CHECK(e);
  });
}
}  // namespace detail

// The first pair (a, b) of `devices` where GPU a cannot reach GPU b's memory; none where the peer
// group can run on them.
inline std::optional<std::pair<int, int>> unreachable_peers(const std::vector<int>& devices) {
  for (int a : devices)
    for (int b : devices) {
      int can = 1;
      if (a != b) EPONA_CUDA_CHECK(cudaDeviceCanAccessPeer(&can, a, b));
      if (!can) return std::pair{a, b};
    }
  return std::nullopt;
}

template <class A>
class PeerShardGroup : public DeviceShardThreads {
  static_assert(std::is_same_v<A, float> || std::is_same_v<A, bf16>, "PeerShardGroup: float or bf16 activations");

 public:
  // Shard r on GPU devices[r]; every pair must reach each other's memory.
  explicit PeerShardGroup(std::vector<int> devices, PeerGroupOptions options = {})
      : DeviceShardThreads(std::move(devices), "PeerShardGroup", detail::kMaxPeerShards, options.share_devices),
        options_(options), counts_(static_cast<std::size_t>(size())) {
    EPONA_CHECK(options_.capacity >= detail::kPack && options_.capacity % detail::kPack == 0,
                "PeerShardGroup: capacity ", options_.capacity, " (a positive multiple of ", detail::kPack, ")");
    EPONA_CHECK(options_.blocks >= 1 && options_.blocks <= detail::kMaxPeerBlocks, "PeerShardGroup: ", options_.blocks,
                " blocks (1 to ", detail::kMaxPeerBlocks, ")");
    int current = 0;
    EPONA_CUDA_CHECK(cudaGetDevice(&current));
    try {
      enable_peer_access();
      allocate();
    } catch (...) {
      (void)cudaSetDevice(current);
      throw;
    }
    EPONA_CUDA_CHECK(cudaSetDevice(current));
  }
  PeerShardGroup(const PeerShardGroup&) = delete;
  PeerShardGroup& operator=(const PeerShardGroup&) = delete;

  const PeerGroupOptions& options() const { return options_; }

  using Sum = GroupShardSum<PeerShardGroup, Context, A>;
  Sum shard(std::int64_t rank) { return Sum(*this, rank); }

  // Shard `rank`'s sum on its context's stream (its ShardSum's call). The ranks' threads meet
  // before (the sizes must agree) and after the launch; while the stream records a graph, the
  // graph's launches are fenced instead.
  void sum(Context& ctx, std::int64_t rank, A* data, std::int64_t count) {
    if (size() == 1) return;
    EPONA_CHECK(ctx.info().device == device(rank), "PeerShardGroup: shard ", rank, " summed on GPU ",
                ctx.info().device, ", but its GPU is ", device(rank));
    counts_[static_cast<std::size_t>(rank)] = count;
    fence();  // every rank's count is in; none changes before the fence after the launch
    EPONA_CHECK(std::all_of(counts_.begin(), counts_.end(), [&](std::int64_t c) { return c == count; }),
                "PeerShardGroup: the shards summed buffers of different sizes");
    (void)fence_recorded_graph(ctx);  // the launches below then only record
    for (std::int64_t done = 0; done < count; done += options_.capacity)
      launch(ctx, rank, data + done, std::min(options_.capacity, count - done));
    fence();
  }

 private:
  // Every GPU of the group maps every other's memory (a pair that cannot is refused by name).
  void enable_peer_access() {
    if (const auto pair = unreachable_peers(devices()))
      fail("PeerShardGroup: GPU ", pair->first, " cannot reach GPU ", pair->second,
           "'s memory (no NVLink or PCIe peer access); use the NCCL group (--shard-sum nccl)");
    for (int a : devices())
      for (int b : devices())
        if (a != b) detail::map_peer_memory(a, b);
  }

  void allocate() {
    const std::size_t n = devices().size(), flags = sizeof(unsigned) * detail::kMaxPeerBlocks * detail::kMaxPeerShards;
    const std::size_t epochs = sizeof(unsigned) * detail::kMaxPeerBlocks;
    capacity_bytes_ = options_.capacity * static_cast<std::int64_t>(sizeof(A));
    const std::size_t inbox = 2 * n * static_cast<std::size_t>(capacity_bytes_);
    for (std::size_t r = 0; r < n; ++r) {
      EPONA_CUDA_CHECK(cudaSetDevice(devices()[r]));
      memory_.push_back(BackendMemory<Cuda>::allocate(inbox + flags + epochs));
      EPONA_CUDA_CHECK(cudaMemset(memory_.back().get(), 0, inbox + flags + epochs));
    }
    for (std::size_t r = 0; r < n; ++r) {
      auto* base = static_cast<unsigned char*>(memory_[r].get());
      inboxes_.push_back(base);
      flags_.push_back(reinterpret_cast<unsigned*>(base + inbox));
      epochs_.push_back(reinterpret_cast<unsigned*>(base + inbox + flags));
    }
    for (const int d : devices()) {
      EPONA_CUDA_CHECK(cudaSetDevice(d));
      EPONA_CUDA_CHECK(cudaDeviceSynchronize());
    }
  }

  void launch(Context& ctx, std::int64_t rank, A* data, std::int64_t count) {
    detail::PeerLinks links{};
    for (std::size_t j = 0; j < devices().size(); ++j) {
      links.inbox_of[j] = inboxes_[j];
      links.flags_of[j] = flags_[j];
    }
    links.epochs = epochs_[static_cast<std::size_t>(rank)];
    links.rank = static_cast<int>(rank);
    links.size = static_cast<int>(size());
    links.capacity_bytes = capacity_bytes_;
    const bool packed = count % detail::kPack == 0 && detail::aligned16(data);
    detail::peer_sum_kernel<A><<<options_.blocks, detail::kPeerSumThreads, 0, ctx.stream()>>>(links, data, count, packed);
    EPONA_CUDA_CHECK(cudaGetLastError());
  }

  PeerGroupOptions options_;
  std::vector<std::int64_t> counts_;
  std::vector<std::shared_ptr<void>> memory_;
  std::vector<unsigned char*> inboxes_;
  std::vector<unsigned*> flags_, epochs_;
  std::int64_t capacity_bytes_ = 0;
};

}  // namespace epona::cuda
