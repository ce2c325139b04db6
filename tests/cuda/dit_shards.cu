// Tensor parallelism of the DiTs on the GPU (core/tensor_parallel.hpp, docs/parallel.md): a DiT split
// over 2 and 4 shards, each shard a host thread with its own context and its weights cut from
// the whole model's map, samples (Heun, 4 steps) what the whole DiT samples. On one GPU the shards
// share it (cuda::StreamShardGroup with graphs off, and cuda::PeerShardGroup with the sampler's graph
// holding its sums); with two GPUs the shards are GPUs (cuda::PeerShardGroup, and
// cuda::NcclShardGroup where the build has NCCL), else those cases skip with a message. A VisDiT-like DiT (an action, paired streams at one item) and a TrajDiT-like one (the
// pipelined condition front), head dim 128 as the real model's, one item and a batch of two.
// (The world model with its VisDiT split: tests/cuda/world_parity.cu.)
// Scratch is poisoned (NaN) and every output checked finite.
// Bounds (check_shard_results, cuda_test_util.cuh): float32 within 1e-5 relative L2 of the whole
// DiT on the GPU, bf16 within 1.5x the whole bf16 DiT's own distance from float32 plus 4e-3, and
// every shard the same bits.
#include "cuda_test_util.cuh"
#include "watchdog.hpp"

#include <chrono>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "../metrics.hpp"
#include "../model/dit_cases.hpp"
#include "epona/cuda/backend.cuh"
#include "epona/cuda/runtime/graph.hpp"
#include "epona/cuda/runtime/peer_shard_sum.cuh"
#include "epona/cuda/runtime/stream_shard_sum.cuh"
#include "epona/model/flux_dit.hpp"
#if defined(EPONA_TEST_NCCL)
#include "epona/cuda/runtime/nccl_shard_sum.hpp"
#endif

using namespace epona;
using namespace epona::test;
using test::dit::Case;
using test::dit::Inputs;

namespace {

constexpr std::int64_t kSteps = 4;

template <class W> using GpuDit = model::FluxDiT<Cuda, W>;

// The shared test DiTs at the real head dim (128) and four heads.
Case gpu_case(Case k) {
  k.config.hidden_size = 512;
  k.config.num_heads = 4;
  k.config.axes_dim = {16, 56, 56};
  k.config.context_in_dim = 64;
  k.rows = {37, k.rows.target == 9 ? 34 : 5};
  if (k.config.vec_in_dim > 0) k.config.in_channels = k.config.out_channels = 32;
  return k;
}

template <class M>
void bind(M& dit, const io::TensorMap& map) {
  io::BindReport report(map);
  dit.bind(map, "", report);
  report.finish(true, [](const std::string&) { return false; });
}

// A Heun sample of `in` on the GPU context `ctx` (its scratch poisoned).
template <class W>
HostF gpu_sample(cuda::Context& ctx, const GpuDit<W>& dit, const Inputs& in) {
  const std::int64_t batch = in.x.size(0);
  const nn::JointRows rows{in.cond.size(1), in.x.size(1)};
  const auto kind = flow::SolverKind::heun;
  ScopedPolicy poison(ctx.policy().poison_new_buffers, true);
  Arena<Cuda> arena(dit.conditioning_bytes(batch, rows) + dit.sample_bytes(batch, rows, kSteps, kind));
  auto cond = upload<float>(ctx, in.cond);
  auto y = in.y.empty() ? Dev<float>() : upload<float>(ctx, in.y);
  auto x = upload<float>(ctx, in.x);
  const auto c = dit.prepare(ctx, arena, cond, in.cond_ids, in.target_ids, y);
  dit.sample(ctx, arena, c, flow::get_schedule(kSteps, rows.target), x, kind);
  return download(ctx, x);
}

// Every shard's sample from a `Group` of `shards` (cuda::StreamShardGroup or NcclShardGroup).
template <class W, class Group, class Device>
std::vector<HostF> shard_samples(Group& group, const Case& k, const io::TensorMap& weights, const Inputs& in,
                                 Device device_of, bool graphs) {
  const std::int64_t shards = group.size();
  std::vector<HostF> out(static_cast<std::size_t>(shards));
  group.run([&](std::int64_t r) {
    cuda::Context ctx(device_of(r));
    ctx.policy().graphs = graphs;
    ctx.policy().gemm_tuning = cuda::GemmTuning::Off;  // the same kernels on every shard
    model::FluxDitConfig config = k.config;
    config.shard = {r, shards};
    GpuDit<W> part(config);
    bind(part, part.shard_weights(weights, ""));
    const auto sum = group.shard(r);
    part.set_shard_sum(&sum);
    out[static_cast<std::size_t>(r)] = gpu_sample(ctx, part, in);
    ctx.synchronize();
  });
  return out;
}

// Where the shards of sharded_like_whole run, and which group sums for them.
enum class Layout {
  streams_one_gpu,  // StreamShardGroup: 2 and 4 shards sharing GPU 0, graphs off
  peer_one_gpu,     // PeerShardGroup: 2 and 4 shards sharing GPU 0, graphs on
  nccl_two_gpus,    // NcclShardGroup over GPUs 0 and 1, graphs on
  peer_two_gpus,    // PeerShardGroup over GPUs 0 and 1, graphs on
};

template <class W>
void sharded_like_whole(Layout layout) {
  for (const Case& base : {test::dit::vis_like(), test::dit::traj_like()}) {
    const Case k = gpu_case(base);
    const io::TensorMap weights =
        GpuDit<W>(k.config).parameters().random_map(7, "random DiT", nn::WeightInit::torch_linear);
    for (const std::int64_t items : {1, 2}) {
      const Inputs in = test::dit::inputs(k, items);
      HostF whole, f32;
      {
        cuda::Context ctx;
        GpuDit<W> dit(k.config);
        bind(dit, weights);
        whole = gpu_sample(ctx, dit, in);
        GpuDit<float> dit32(k.config);
        bind(dit32, weights);
        f32 = gpu_sample(ctx, dit32, in);
      }
      const std::string what = std::string(k.name) + ", " + type_name<W>() + ", " + std::to_string(items) + " item(s)";
      const auto on_gpu0 = [](std::int64_t) { return 0; };
      const auto own_gpu = [](std::int64_t r) { return int(r); };
      for (const std::int64_t shards : {2, 4}) {
        const std::string on_one = what + ", " + std::to_string(shards) + " shards on one GPU";
        if (layout == Layout::streams_one_gpu) {
          cuda::StreamShardGroup<W> group(shards);
          check_shard_results<W>(shard_samples<W>(group, k, weights, in, on_gpu0, false), whole, f32, on_one);
        }
        if (layout == Layout::peer_one_gpu) {
          // Few blocks: a shard's waiting sum must leave the others' products room on the GPU.
          cuda::PeerShardGroup<W> group(std::vector<int>(static_cast<std::size_t>(shards), 0),
                                        {.blocks = 8, .share_devices = true});
          check_shard_results<W>(shard_samples<W>(group, k, weights, in, on_gpu0, true), whole, f32,
                                 on_one + " through the peer group (graphs on)");
        }
      }
      if (layout == Layout::peer_two_gpus) {
        cuda::PeerShardGroup<W> group({0, 1});
        check_shard_results<W>(shard_samples<W>(group, k, weights, in, own_gpu, true), whole, f32,
                               what + ", 2 GPUs through the peer group (graphs on)");
      }
#if defined(EPONA_TEST_NCCL)
      if (layout == Layout::nccl_two_gpus) {
        cuda::NcclShardGroup<W> group({0, 1});
        check_shard_results<W>(shard_samples<W>(group, k, weights, in, own_gpu, true), whole, f32,
                               what + ", 2 GPUs through NCCL (graphs on)");
      }
#endif
    }
  }
}

#if defined(EPONA_TEST_NCCL)
// True where two GPUs can hold an NCCL group (else the case skips with a message); NVLink
// multicast must be off, as on the lent machines (docs/parallel.md).
bool two_gpus_for_nccl() {
  if (!two_gpus("the NCCL group")) return false;
  const char* nvls = std::getenv("NCCL_NVLS_ENABLE");
  REQUIRE_MESSAGE((nvls && std::string(nvls) == "0"), "set NCCL_NVLS_ENABLE=0 (docs/parallel.md)");
  return true;
}

// CUDA calls that can wait on a device while they hold the driver's locks: cudaMalloc, pageable
// copies, cudaFree.
void busy_with_memory(cuda::Context& ctx) {
  std::vector<float> host(1 << 22, 1.f);
  for (int i = 0; i < 8; ++i) {
    void* p = nullptr;
    EPONA_CUDA_CHECK(cudaMalloc(&p, host.size() * sizeof(float)));
    EPONA_CUDA_CHECK(cudaMemcpy(p, host.data(), host.size() * sizeof(float), cudaMemcpyHostToDevice));
    EPONA_CUDA_CHECK(cudaMemcpy(host.data(), p, host.size() * sizeof(float), cudaMemcpyDeviceToHost));
    EPONA_CUDA_CHECK(cudaFree(p));
  }
  ctx.synchronize();
}
#endif

}  // namespace

TEST_CASE_TEMPLATE("a DiT split over shards sharing one GPU samples what the whole DiT samples", W, float, bf16) {
  EPONA_REQUIRE_GPU();
  sharded_like_whole<W>(Layout::streams_one_gpu);
}

TEST_CASE_TEMPLATE("a DiT split over two GPUs through NCCL samples what the whole DiT samples", W, float, bf16) {
  EPONA_REQUIRE_GPU();
#if defined(EPONA_TEST_NCCL)
  if (!two_gpus_for_nccl()) return;
  Watchdog watchdog("a DiT over two GPUs through NCCL", 300);
  sharded_like_whole<W>(Layout::nccl_two_gpus);
#else
  MESSAGE("built without NCCL: skipping");
#endif
}

TEST_CASE_TEMPLATE("a DiT split over shards sharing one GPU through the peer group samples what the whole DiT samples",
                   W, float, bf16) {
  EPONA_REQUIRE_GPU();
  Watchdog watchdog("a DiT over shards sharing one GPU through the peer group", 300);
  sharded_like_whole<W>(Layout::peer_one_gpu);
}

TEST_CASE_TEMPLATE("a DiT split over two GPUs through the peer group samples what the whole DiT samples", W, float,
                   bf16) {
  EPONA_REQUIRE_GPU();
  if (!two_gpus("the peer group over GPUs")) return;
  Watchdog watchdog("a DiT over two GPUs through the peer group", 300);
  sharded_like_whole<W>(Layout::peer_two_gpus);
}

TEST_CASE("the NCCL group of one GPU: its sum runs, directly and inside a recorded graph") {
  EPONA_REQUIRE_GPU();
#if defined(EPONA_TEST_NCCL)
  // One rank sums to itself; what this checks is the call (types, in place, on the context's
  // stream) and its capture into a graph, which the sampler records. Two GPUs: the case above.
  cuda::NcclShardGroup<bf16> group({0});
  CHECK_THROWS_WITH_AS(cuda::NcclShardGroup<bf16>({0, 0}), doctest::Contains("device 0 twice"), Error);
  CHECK_THROWS_WITH_AS(cuda::NcclShardGroup<bf16>({0, 99}), doctest::Contains("device 99 does not exist"), Error);
  group.run([&](std::int64_t r) {
    cuda::Context ctx;
    HostF values = random_tensor({1000}, 3);
    round_to<bf16>(values);
    Dev<bf16> d = upload<bf16>(ctx, values);
    const auto sum = group.shard(r);
    sum.sum(ctx, d.data(), d.numel());
    cuda::GraphCache graph;
    for (int i = 0; i < 2; ++i) graph.run(ctx, {1}, [&] { sum.sum(ctx, d.data(), d.numel()); });
    CHECK(graph.captures() == 1);
    CHECK_FALSE(graph.holds_collectives());  // a group of one has no peer to fence with
    CHECK(count_bit_differences(download(ctx, d), values) == 0);
  });
#else
  MESSAGE("built without NCCL: skipping");
#endif
}

TEST_CASE("a recorded graph holding a collective calls its group's fence before and after every launch") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  ctx.policy().graphs = true;
  Dev<float> d({4});
  int fences = 0;
  cuda::GraphCache graph;
  const auto work = [&](bool collective) {
    return [&, collective] {
      EPONA_CUDA_CHECK(cudaMemsetAsync(d.data(), 0, d.nbytes(), ctx.stream()));
      if (collective) ctx.note_captured_collective([&] { ++fences; });
    };
  };
  graph.run(ctx, {1}, work(true));
  CHECK(graph.holds_collectives());
  CHECK(fences == 2);  // the recording calls nothing; its first launch two
  graph.run(ctx, {1}, work(true));
  CHECK(fences == 4);
  graph.run(ctx, {2}, work(false));  // a new recording without one forgets the fence
  CHECK_FALSE(graph.holds_collectives());
  graph.run(ctx, {2}, work(false));
  CHECK(fences == 4);
  CHECK_FALSE(static_cast<bool>(ctx.take_captured_collective()));
  ctx.synchronize();
}

#if defined(EPONA_TEST_NCCL)
TEST_CASE("the NCCL group over two GPUs: a rank busy with memory calls while the other sums does not stall it") {
  EPONA_REQUIRE_GPU();
  if (!two_gpus_for_nccl()) return;
  // Rank 1 makes those calls after rank 0 reached its sum, and rank 0 after its sum: without the
  // group's fences rank 0's all-reduce would wait for rank 1, whose calls wait for GPU 0.
  Watchdog watchdog("NCCL group with memory calls beside its sums", 120);
  cuda::NcclShardGroup<float> group({0, 1});
  const HostF a = random_tensor({4096}, 5), b = random_tensor({4096}, 6);
  for (const bool graphs : {false, true}) {
    std::vector<HostF> out(2);
    group.run([&](std::int64_t r) {
      cuda::Context ctx;
      ctx.policy().graphs = graphs;
      Dev<float> d = upload<float>(ctx, r == 0 ? a : b);
      const auto sum = group.shard(r);
      cuda::GraphCache graph;
      for (int round = 0; round < 3; ++round) {
        if (r == 1) {
          std::this_thread::sleep_for(std::chrono::milliseconds(100));
          busy_with_memory(ctx);
        }
        // Three sums: each round doubles the first round's sum (a + b, then 2(a + b), 4(a + b)).
        graph.run(ctx, {1}, [&] { sum.sum(ctx, d.data(), d.numel()); });
        if (r == 0) busy_with_memory(ctx);
      }
      CHECK(graph.holds_collectives() == graphs);
      out[static_cast<std::size_t>(r)] = download(ctx, d);
    });
    std::int64_t wrong = 0;
    for (std::int64_t i = 0; i < a.numel(); ++i) {
      // a + b rounded once, then doubled twice (exact): 2 ranks sum in one addition.
      const float expected = 4.f * (a.data()[i] + b.data()[i]);
      wrong += out[0].data()[i] != expected || out[1].data()[i] != expected;
    }
    CHECK_MESSAGE(wrong == 0, (graphs ? "graphs" : "eager"), ": ", wrong, " of ", a.numel(), " sums wrong");
  }
}
#endif

TEST_CASE("the one-GPU group refuses graphs, and sums of different sizes") {
  EPONA_REQUIRE_GPU();
  cuda::StreamShardGroup<float> group(2);
  Dev<float> a({8}), b({8});
  CHECK_THROWS_WITH_AS(group.run([&](std::int64_t r) {
                         cuda::Context ctx;
                         ctx.policy().graphs = r == 0;
                         group.shard(r).sum(ctx, (r == 0 ? a : b).data(), 8);
                       }),
                       doctest::Contains("graphs off"), Error);
  cuda::StreamShardGroup<float> uneven(2);
  CHECK_THROWS_WITH_AS(uneven.run([&](std::int64_t r) {
                         cuda::Context ctx;
                         ctx.policy().graphs = false;
                         uneven.shard(r).sum(ctx, (r == 0 ? a : b).data(), r + 4);
                       }),
                       doctest::Contains("different sizes"), Error);
  // A correct sum: 1..8 and 10..80, on both shards.
  cuda::StreamShardGroup<float> sums(2);
  HostF ha({8}), hb({8});
  for (int i = 0; i < 8; ++i) ha.data()[i] = float(i + 1), hb.data()[i] = float(10 * (i + 1));
  cuda::Context ctx;
  Dev<float> da = upload<float>(ctx, ha), db = upload<float>(ctx, hb);
  ctx.synchronize();
  sums.run([&](std::int64_t r) {
    cuda::Context ctx;
    ctx.policy().graphs = false;
    sums.shard(r).sum(ctx, (r == 0 ? da : db).data(), 8);
    ctx.synchronize();
  });
  const HostF ra = download(ctx, da), rb = download(ctx, db);
  for (int i = 0; i < 8; ++i) {
    CHECK(ra.data()[i] == float(11 * (i + 1)));
    CHECK(rb.data()[i] == ra.data()[i]);
  }
}
