// bench_gpu_shards — issue #40's tensor parallelism of the VisDiT (docs/parallel.md) at the real
// configuration (512x1024 frames, the shipped widths and depths, bf16, random weights, one item).
// vis_* rows: the VisDiT's `steps`-step sample (its recorded graph replayed); step_* rows: an AR
// step, WorldModel::predict_next (MST + TrajDiT + VisDiT, `steps` steps each, self-predicted
// action; the MST and TrajDiT whole on every shard, the VisDiT split). Each kind as
//   *_whole          the whole model on GPU 0
//   *_shardN_alone   one shard of an N-way split (N = 2, 4) on GPU 0, its sums left out: the
//                    products, attention and row passes one of N GPUs would run, without collectives
//   *_peerN          (N GPUs present) the N-way split over GPUs 0..N-1 through the peer group
//                    (cuda/runtime/peer_shard_sum.cuh; --peer-blocks B its kernel's blocks), one host
//                    thread per GPU; every rank starts each repeat together and the row is rank 0's time
//   *_ncclN          (and the program built with NCCL) the same through NCCL
// Each row: median milliseconds over the repeats (CUDA events, after a warm-up call that records
// the graphs), the same per step, and the whole model's time over it. *_peerN - *_shardN_alone is
// the time the collectives add (none of it is hidden: docs/parallel.md, "Hiding the sums"). Prints
// one JSON line per row.
// rollout_* rows: issue #40's AR step + decode. Rollouts of 5 frames, each frame's DC-AE decode (the
// real DC-AE, random weights, bf16) on a stream and host thread of its own on GPU 0 while the next
// step samples (as the epona program's FrameDecoder runs it); milliseconds per frame: whole (one
// GPU) and the split over N GPUs (*_peerN, *_ncclN as above).
// sum_* rows: one sum of a VisDiT block's output (1027 x 2048 bf16, 4.2 MB) over N GPUs, 50 in a
// recorded graph, microseconds per sum: sum_peerN_blocksB (the peer group's kernel in B blocks)
// and sum_ncclN (NCCL's all-reduce).
// block_* and attention_* rows: tensor against sequence parallelism on one block (issue #40 asks for
// both on at least one block). One VisDiT block (bf16, one item, S = 1027 joint rows), 50 calls in
// a recorded graph, milliseconds per call:
//   block_{double,single}_whole      the whole block over the S rows
//   block_..._tp{N}_alone            a tensor-parallel shard (heads/N, MLP columns/N), sums left out
//   block_..._rows{N}                the whole-width block over S/N rows: a sequence shard's products,
//                                    norms and residual passes, with attention over its own rows only
//   attention_whole                  the joint attention of the whole block (inside block_..._whole)
//   attention_rows{N}                the joint attention of S/N rows, every head (inside rows{N})
//   attention_heads{N}               the joint attention of all S rows, heads/N: what a sequence shard
//                                    attends after Ulysses' all-to-all (and a tensor-parallel shard)
//   block_..._sp{N}_alone            rows{N} - attention_rows{N} + attention_heads{N}: an estimate
//                                    of a Ulysses sequence shard's compute, without its all-to-alls
//   bench_gpu_shards [--steps S] [--repeats N] [--gpus N] [--peer-blocks B] [--only vis|step|rollout|block|sum]
// Keep NVLink multicast off (NCCL_NVLS_ENABLE=0): the NCCL rows refuse to run with it on.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <future>
#include <memory>
#include <string>
#include <vector>

#include "epona/core/arena.hpp"
#include "epona/core/rng.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/cuda/backend.cuh"
#include "epona/flow/schedule.hpp"
#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"
#include "bench_stats.hpp"
#include "gpu_event_timer.cuh"
#include "gpu_frame_decode.cuh"
#include "epona/cuda/runtime/graph.hpp"
#include "epona/cuda/runtime/peer_shard_sum.cuh"
#if defined(EPONA_BENCH_NCCL)
#include "epona/cuda/runtime/nccl_shard_sum.hpp"
#endif

using namespace epona;

namespace {

using Dit = model::FluxDiT<Cuda, bf16>;

struct Options {
  std::int64_t steps = 100;
  int repeats = 5, gpus = 0;  // gpus 0: every GPU present
  int peer_blocks = cuda::PeerGroupOptions{}.blocks;
  std::string only;           // vis, step, rollout, block or sum; empty: all
  bool want(const std::string& kind) const { return only.empty() || only == kind; }
};

constexpr const char* kUsage = "--steps S, --repeats N, --gpus N, --peer-blocks B, --only vis|step|rollout|block|sum";

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    EPONA_CHECK(i + 1 < argc, a, " needs a value (", kUsage, ")");
    if (a == "--only") {
      o.only = argv[++i];
      EPONA_CHECK(o.only == "vis" || o.only == "step" || o.only == "rollout" || o.only == "block" || o.only == "sum",
                  "--only takes vis, step, rollout, block or sum, got '", o.only, "'");
      continue;
    }
    char* end = nullptr;
    const long long v = std::strtoll(argv[++i], &end, 10);
    EPONA_CHECK(end && *end == 0 && v >= 1 && v <= 1000, a, " takes a whole number in [1, 1000], got '", argv[i], "'");
    if (a == "--steps") o.steps = v;
    else if (a == "--repeats") o.repeats = int(v);
    else if (a == "--gpus") o.gpus = int(v);
    else if (a == "--peer-blocks") o.peer_blocks = int(v);
    else fail("unknown option '", a, "' (", kUsage, ")");
  }
  return o;
}

// A shard's sums left out: what its GPU computes, without the collectives.
class NoSum final : public ShardSum<cuda::Context, bf16> {
 public:
  explicit NoSum(std::int64_t size) : size_(size) {}
  std::int64_t size() const override { return size_; }
  void sum(cuda::Context&, bf16*, std::int64_t) const override {}

 private:
  std::int64_t size_;
};

// One VisDiT shard (rank of size; size 1: the whole VisDiT) with random weights, its conditioning
// and noise prepared on its own context (on the thread's current device); sample() runs the steps.
struct VisSample {
  cuda::Context ctx;
  Dit dit;
  Arena<Cuda> arena;
  Dit::Conditioning conditioning;
  Tensor<float, Cuda> state;
  std::vector<float> grid;

  VisSample(const WorldModelConfig& cfg, TensorShard shard, std::int64_t steps)
      : dit(config(cfg, shard)), arena(bytes(dit, cfg, steps)) {
    dit.randomize(1);
    const auto ids = model::prepare_ids(1, cfg.latent_h(), cfg.latent_w(), cfg.tokens_per_frame(), cfg.traj_len);
    const nn::JointRows rows{cfg.tokens_per_frame(), ids.img.size(1)};
    TorchGenerator gen(5);
    const auto cond = BackendTraits<Cuda>::upload(gen.randn({1, rows.cond, cfg.context_in_dim()}));
    const auto y = BackendTraits<Cuda>::upload(gen.randn({1, cfg.pose_emb_dim()}));
    state = BackendTraits<Cuda>::upload(gen.randn({1, rows.target, dit.config().in_channels}));
    conditioning = dit.prepare(ctx, arena, cond, ids.cond, ids.img, y);
    grid = flow::get_schedule(steps, rows.target);
  }
  cuda::Context& context() { return ctx; }
  void sample(cuda::Context& c) { dit.sample(c, arena, conditioning, grid, state); }

  static model::FluxDitConfig config(const WorldModelConfig& cfg, TensorShard shard) {
    auto c = model::FluxDitConfig::vis(cfg);
    c.shard = shard;
    return c;
  }
  static std::size_t bytes(const Dit& dit, const WorldModelConfig& cfg, std::int64_t steps) {
    const nn::JointRows rows{cfg.tokens_per_frame(), cfg.img_tokens()};
    return dit.conditioning_bytes(1, rows) + dit.sample_bytes(1, rows, steps);
  }
};

// An AR step of a world model whose VisDiT is shard `shard` (size 1: whole), random weights.
struct WorldStep {
  WorldModel<Cuda, bf16> wm;
  History h;
  SampleOptions opt;

  WorldStep(const io::TensorMap& weights, const WorldModelConfig& cfg, TensorShard shard,
            const WorldModel<Cuda, bf16>::VisShardSum* sum, std::int64_t steps)
      : wm(WorldModel<Cuda, bf16>::load(weights, cfg, {shard, sum})), h(window(cfg)) {
    opt.seed = 7;
    opt.steps = steps;
  }
  cuda::Context& context() { return wm.context(); }
  void sample(cuda::Context&) { (void)wm.predict_next(h, std::nullopt, opt); }
  // A scene driving forward: random latents, about 2 m per frame.
  static History window(const WorldModelConfig& cfg) {
    TorchGenerator gen(11);
    const std::int64_t F = cfg.condition_frames;
    History h{gen.randn({1, F, cfg.img_tokens(), cfg.token_dim()}), gen.randn({1, F, 2}), gen.randn({1, F, 1})};
    for (std::int64_t f = 0; f < F; ++f) h.rel_pose.at(0, f, 0) = 2.0f + 0.5f * h.rel_pose.at(0, f, 0);
    return h;
  }
};

// kFrames AR steps, each frame's DC-AE decode (bench::FrameDecode, on this GPU) on a worker thread
// while the next step samples, as the epona program's FrameDecoder runs it; `decodes` false: the
// steps alone (the other shards').
struct Rollout {
  static constexpr int kFrames = 5;
  WorldStep step;
  std::unique_ptr<bench::FrameDecode<bf16>> decode;

  Rollout(const io::TensorMap& weights, const WorldModelConfig& cfg, TensorShard shard,
          const WorldModel<Cuda, bf16>::VisShardSum* sum, std::int64_t steps, bool decodes)
      : step(weights, cfg, shard, sum, steps),
        decode(decodes ? std::make_unique<bench::FrameDecode<bf16>>(cfg) : nullptr) {}
  cuda::Context& context() { return step.context(); }
  void sample(cuda::Context&) {
    std::future<Tensor<float>> running;
    for (int f = 0; f < kFrames; ++f) {
      const StepResult r = step.wm.predict_next(step.h, std::nullopt, step.opt);
      if (running.valid()) running.get();
      if (decode) running = std::async(std::launch::async, [this, latent = r.latent] { return (*decode)(latent); });
    }
    if (running.valid()) running.get();
  }
};

void emit(const std::string& name, const std::vector<double>& runs, std::int64_t steps, double whole_ms) {
  const double ms = bench::median(runs);
  std::printf("{\"name\": \"%s\", \"ms\": %.3f, \"ms_per_step\": %.4f, \"whole_over_this\": %.3f}\n", name.c_str(), ms,
              ms / double(steps), whole_ms > 0 ? whole_ms / ms : 1.0);
  std::fflush(stdout);
}

// Each run's time over n (milliseconds per frame of a rollout).
std::vector<double> per(std::vector<double> runs, int n) {
  for (double& r : runs) r /= n;
  return runs;
}

// The whole VisDiT and one shard of each split, one after another on GPU 0.
double vis_rows(const Options& o, const WorldModelConfig& cfg) {
  double whole_ms = 0;
  for (const std::int64_t shards : {1, 2, 4}) {
    VisSample s(cfg, {0, shards}, o.steps);
    const NoSum none(shards);
    if (shards > 1) s.dit.set_shard_sum(&none);
    auto& ctx = s.context();
    const auto runs = bench::event_times_ms(ctx, o.repeats, 1, [&] { s.sample(ctx); });
    if (shards == 1) whole_ms = bench::median(runs);
    emit(shards == 1 ? "vis_whole" : "vis_shard" + std::to_string(shards) + "_alone", runs, o.steps, whole_ms);
  }
  return whole_ms;
}

// The same for the AR step: whole, then a world model with one VisDiT shard of each split.
double step_rows(const Options& o, const WorldModelConfig& cfg, const io::TensorMap& weights) {
  double whole_ms = 0;
  for (const std::int64_t shards : {1, 2, 4}) {
    const NoSum none(shards);
    WorldStep s(weights, cfg, {0, shards}, shards > 1 ? &none : nullptr, o.steps);
    auto& ctx = s.wm.context();
    const auto runs = bench::event_times_ms(ctx, o.repeats, 1, [&] { s.sample(ctx); });
    if (shards == 1) whole_ms = bench::median(runs);
    emit(shards == 1 ? "step_whole" : "step_shard" + std::to_string(shards) + "_alone", runs, o.steps, whole_ms);
  }
  return whole_ms;
}

// ---- one block, tensor against sequence parallelism ------------------------------------------

constexpr int kBlockCalls = 50;
using A = Activation<Cuda, bf16>;

// A VisDiT block of `widths` over `rows` with random weights, inputs and RoPE table, timed per call.
template <class Block>
struct BlockRun {
  nn::DitWidths widths;
  nn::JointRows rows;
  Block block;
  NoSum none;
  Arena<Cuda> arena;
  nn::DitScratch<Cuda, A> s;
  nn::RopeTable<Cuda> rope;
  Tensor<A, Cuda> mods;
  nn::SideQueue<Cuda> queue;
  cuda::GraphCache graph;

  BlockRun(cuda::Context& ctx, const nn::DitWidths& w, const nn::JointRows& r, std::int64_t mod_width)
      : widths(w), rows(r), block(w), none(w.shards), arena(scratch_bytes(w, r)),
        s(nn::DitScratch<Cuda, A>::plan(arena, r, w)) {
    block.randomize(3);
    if (w.shards > 1) block.shard_sum = &none;
    TorchGenerator gen(4);
    const auto upload = [](const Tensor<float, Cpu>& t) { return BackendTraits<Cuda>::upload(host_as<A>(t)); };
    cuda::copy(ctx, upload(gen.randn({r.total(), w.hidden})).data(), s.z.data(), r.total() * w.hidden);
    rope = {BackendTraits<Cuda>::upload(gen.randn({r.total(), w.head_dim() / 2})),
            BackendTraits<Cuda>::upload(gen.randn({r.total(), w.head_dim() / 2}))};
    Tensor<float, Cpu> m = gen.randn({mod_width});
    for (std::int64_t i = 0; i < m.numel(); ++i) m.data()[i] *= 0.1f;
    mods = upload(m);
  }
  static std::size_t scratch_bytes(const nn::DitWidths& w, const nn::JointRows& r) {
    ArenaCounter<Cuda> counter;
    nn::DitScratch<Cuda, A>::plan(counter, r, w);
    return counter.bytes();
  }
  void call(cuda::Context& ctx) { block(ctx, queue, s, rows, rope, mods.data()); }
  void attend(cuda::Context& ctx) {
    const std::int64_t I = widths.attention_width();
    nn::detail::joint_attention<Cuda>(ctx, s.qkv.data(), rows.total(), 0, rows.total(), widths, s.attn.data(), I, 3 * I);
  }
  // Median milliseconds per call of the block and of its joint attention alone (on the qkv rows the
  // block left), each kBlockCalls calls in one recorded graph.
  struct Times {
    double block, attention;
  };
  Times times(cuda::Context& ctx, int repeats) {
    const double block_ms = ms_per_call(ctx, repeats, 1, [&] { call(ctx); });
    return {block_ms, ms_per_call(ctx, repeats, 2, [&] { attend(ctx); })};
  }

 private:
  template <class Work>
  double ms_per_call(cuda::Context& ctx, int repeats, std::uint64_t key, Work work) {
    const auto many = [&] {
      for (int i = 0; i < kBlockCalls; ++i) work();
    };
    const auto runs = bench::event_times_ms(ctx, repeats, 1, [&] { graph.run(ctx, {key}, many); });
    return bench::median(runs) / kBlockCalls;
  }
};

void emit_block(const std::string& name, double ms, double whole_ms) {
  std::printf("{\"name\": \"%s\", \"ms\": %.4f, \"whole_over_this\": %.3f}\n", name.c_str(), ms, whole_ms / ms);
  std::fflush(stdout);
}

// Both kinds of block: whole, tensor-parallel shards, and the parts of a sequence shard's estimate.
template <class Block>
void block_rows(cuda::Context& ctx, const Options& o, const WorldModelConfig& cfg, const std::string& kind,
                std::int64_t mod_blocks) {
  const nn::DitWidths whole = model::FluxDitConfig::vis(cfg).widths();
  const nn::JointRows all{cfg.tokens_per_frame(), cfg.img_tokens()};
  const auto time = [&](const nn::DitWidths& w, const nn::JointRows& r) {
    return BlockRun<Block>(ctx, w, r, mod_blocks * w.hidden).times(ctx, o.repeats);
  };
  const auto whole_times = time(whole, all);
  const double whole_ms = whole_times.block;
  emit_block("block_" + kind + "_whole", whole_ms, whole_ms);
  emit_block("attention_whole_" + kind, whole_times.attention, whole_ms);
  for (const std::int64_t n : {2, 4}) {
    nn::DitWidths shard = whole;
    shard.shards = n;
    const nn::JointRows part{(all.cond + n - 1) / n, (all.target + n - 1) / n};
    const auto tp = time(shard, all), rows = time(whole, part);  // tp.attention: all rows, heads/N
    const std::string N = std::to_string(n);
    emit_block("block_" + kind + "_tp" + N + "_alone", tp.block, whole_ms);
    emit_block("block_" + kind + "_rows" + N, rows.block, whole_ms);
    emit_block("attention_rows" + N + "_" + kind, rows.attention, whole_ms);
    emit_block("attention_heads" + N + "_" + kind, tp.attention, whole_ms);
    emit_block("block_" + kind + "_sp" + N + "_alone", rows.block - rows.attention + tp.attention, whole_ms);
  }
}

// Rank 0's milliseconds for `repeats` calls of work->sample(ctx) over `group` (one GPU per rank),
// each rank's work made by make(rank, sum) in its thread (on its GPU), after a warm-up call that
// records the graphs; every rank starts each call together.
template <class Group, class Make>
std::vector<double> rank0_times(Group& group, int repeats, const Make& make) {
  BreakableBarrier together(group.size());
  std::vector<double> rank0;
  group.run([&](std::int64_t r) {
    const auto sum = group.shard(r);
    auto work = make(r, sum);
    auto& ctx = work->context();
    work->sample(ctx);
    ctx.synchronize();
    std::vector<double> runs;
    for (int i = 0; i < repeats; ++i) {
      together.arrive_and_wait();
      runs.push_back(bench::event_times_ms(ctx, 1, 0, [&] { work->sample(ctx); }).front());
    }
    if (r == 0) rank0 = runs;
  });
  return rank0;
}

// The N-way split over GPUs 0..N-1 through `group`: rank 0's times, over `per_call` (frames a call).
template <class Group, class Make>
void group_row(const Options& o, Group& group, const std::string& row, double whole_ms, const Make& make,
               int per_call) {
  emit(row, per(rank0_times(group, o.repeats, make), per_call), o.steps, whole_ms);
}

std::vector<int> first_gpus(int n) {
  std::vector<int> devices(static_cast<std::size_t>(n));
  for (int d = 0; d < n; ++d) devices[static_cast<std::size_t>(d)] = d;
  return devices;
}

// The N-way split through each group this build has: *_peerN (ours) and *_ncclN.
template <class Make>
void group_rows(const Options& o, const std::string& name, int gpus, double whole_ms, const Make& make,
                int per_call = 1) {
  const std::string n = std::to_string(gpus);
  {
    cuda::PeerShardGroup<bf16> peer(first_gpus(gpus), {.blocks = o.peer_blocks});
    group_row(o, peer, name + "_peer" + n, whole_ms, make, per_call);
  }
#if defined(EPONA_BENCH_NCCL)
  cuda::NcclShardGroup<bf16> nccl(first_gpus(gpus));
  group_row(o, nccl, name + "_nccl" + n, whole_ms, make, per_call);
#endif
}

// One sum of a VisDiT block's output (1027 x 2048 bf16, 4.2 MB), 50 of them in a recorded graph
// on one rank's GPU.
struct BlockSums {
  static constexpr int kSums = 50;
  static constexpr std::int64_t kCount = 1027 * 2048;
  cuda::Context ctx;
  Tensor<bf16, Cuda> data{Shape{kCount}};
  const ShardSum<cuda::Context, bf16>& sum;
  cuda::GraphCache graph;

  explicit BlockSums(const ShardSum<cuda::Context, bf16>& s) : sum(s) {
    EPONA_CUDA_CHECK(cudaMemsetAsync(data.data(), 0, data.nbytes(), ctx.stream()));
  }
  cuda::Context& context() { return ctx; }
  void sample(cuda::Context& c) {
    graph.run(c, {1}, [&] {
      for (int i = 0; i < kSums; ++i) sum.sum(c, data.data(), kCount);
    });
  }
};

// One sum over `group`: rank 0's median microseconds per sum.
template <class Group>
void sum_row(const Options& o, Group& group, const std::string& row) {
  const auto runs = rank0_times(group, std::max(o.repeats, 5), [](std::int64_t, const auto& sum) {
    return std::make_unique<BlockSums>(sum);
  });
  std::printf("{\"row\": \"%s\", \"bytes\": %lld, \"us_per_sum\": %.2f}\n", row.c_str(),
              static_cast<long long>(BlockSums::kCount * sizeof(bf16)), bench::median(runs) * 1000.0 / BlockSums::kSums);
}

void sum_rows(const Options& o, int gpus) {
  const std::string n = std::to_string(gpus);
  for (const int blocks : {16, 32, 64, 128, 256}) {
    cuda::PeerShardGroup<bf16> peer(first_gpus(gpus), {.blocks = blocks});
    sum_row(o, peer, "sum_peer" + n + "_blocks" + std::to_string(blocks));
  }
#if defined(EPONA_BENCH_NCCL)
  cuda::NcclShardGroup<bf16> nccl(first_gpus(gpus));
  sum_row(o, nccl, "sum_nccl" + n);
#endif
}

}  // namespace

int main(int argc, char** argv) try {
  const Options o = parse(argc, argv);
  WorldModelConfig cfg;  // the shipped configuration
  int present = 0;
  EPONA_CUDA_CHECK(cudaGetDeviceCount(&present));
  const int gpus = o.gpus ? std::min(o.gpus, present) : present;
  std::printf("# %s; bf16, %lld steps, repeats %d, %d GPU(s)\n", cuda::DeviceInfo::query(0).name.c_str(),
              static_cast<long long>(o.steps), o.repeats, gpus);
#if defined(EPONA_BENCH_NCCL)
  const char* nvls = std::getenv("NCCL_NVLS_ENABLE");
  EPONA_CHECK(gpus < 2 || (nvls && std::string(nvls) == "0"), "set NCCL_NVLS_ENABLE=0 (docs/parallel.md)");
#else
  if (gpus >= 2) std::printf("# built without NCCL: the rows over several GPUs through the peer group only\n");
#endif
  if (o.want("vis")) {
    const double whole_ms = vis_rows(o, cfg);
    for (int n = 2; n <= gpus; n *= 2)
      group_rows(o, "vis", n, whole_ms, [&](std::int64_t r, const auto& sum) {
        auto s = std::make_unique<VisSample>(cfg, TensorShard{r, n}, o.steps);
        s->dit.set_shard_sum(&sum);
        return s;
      });
  }
  if (o.want("sum"))
    for (int n = 2; n <= gpus; n *= 2) sum_rows(o, n);
  if (o.want("block")) {
    cuda::Context ctx;
    block_rows<nn::DoubleStreamBlock<Cuda, bf16>>(ctx, o, cfg, "double", 12);
    block_rows<nn::SingleStreamBlock<Cuda, bf16>>(ctx, o, cfg, "single", 3);
  }
  if (o.want("rollout")) {
    const io::TensorMap weights = model::random_world_weights(cfg, 1);
    double whole_ms = 0;
    {
      Rollout whole(weights, cfg, {0, 1}, nullptr, o.steps, true);
      auto& ctx = whole.context();
      const auto runs = per(bench::event_times_ms(ctx, o.repeats, 1, [&] { whole.sample(ctx); }), Rollout::kFrames);
      whole_ms = bench::median(runs);
      emit("rollout_whole", runs, o.steps, whole_ms);
    }
    for (int n = 2; n <= gpus; n *= 2)
      group_rows(
          o, "rollout", n, whole_ms,
          [&](std::int64_t r, const auto& sum) {
            return std::make_unique<Rollout>(weights, cfg, TensorShard{r, n}, &sum, o.steps, r == 0);
          },
          Rollout::kFrames);
  }
  if (o.want("step")) {
    const io::TensorMap weights = model::random_world_weights(cfg, 1);
    const double whole_ms = step_rows(o, cfg, weights);
    for (int n = 2; n <= gpus; n *= 2)
      group_rows(o, "step", n, whole_ms, [&](std::int64_t r, const auto& sum) {
        return std::make_unique<WorldStep>(weights, cfg, TensorShard{r, n}, &sum, o.steps);
      });
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "bench_gpu_shards: %s\n", e.what());
  return 1;
}
