// The peer group's sum (cuda/runtime/peer_shard_sum.cuh, docs/parallel.md): every rank's buffer ends
// as the parts added in rank order in float32 and rounded once to the activation type, the same
// bits on every rank (checked against that sum computed here), for sizes that fill whole packs and
// those that do not, a misaligned buffer, sums larger than the inboxes (in pieces), directly and
// replayed from recorded graphs (the epochs and inbox slots go on counting across launches), over
// shards sharing one GPU and over two GPUs where the machine has them. Misuse is refused by name.
// (The DiT split over the group: tests/cuda/dit_shards.cu.)
#include "cuda_test_util.cuh"
#include "watchdog.hpp"

#include <string>
#include <vector>

#include "epona/cuda/runtime/graph.hpp"
#include "epona/cuda/runtime/peer_shard_sum.cuh"

using namespace epona;
using namespace epona::test;

namespace {

// Rank r's part for round `round`: values of several magnitudes, rounded to A.
template <class A>
HostF part_of(std::int64_t n, std::int64_t r, int round) {
  HostF t = random_tensor({n}, static_cast<std::uint32_t>(1000 * round + 17 * r + n), -1.f, 1.f);
  for (std::int64_t i = 0; i < n; ++i) t.data()[i] *= float(1 << (i % 7));
  return round_to<A>(t);
}

// The sum every rank must hold: parts in rank order in float32, rounded once to A.
template <class A>
HostF expected_sum(const std::vector<HostF>& parts) {
  HostF out = parts[0];
  for (std::int64_t i = 0; i < out.numel(); ++i) {
    float acc = parts[0].data()[i];
    for (std::size_t j = 1; j < parts.size(); ++j) acc += parts[j].data()[i];
    out.data()[i] = acc;
  }
  return round_to<A>(out);
}

// Runs `rounds` sums of `n` elements (offset elements into their allocation) on every rank of
// `group`, directly or through a recorded graph (new parts copied in before each launch), and
// checks each round's result on every rank, bit for bit.
template <class A>
void check_sums(cuda::PeerShardGroup<A>& group, std::int64_t n, std::int64_t offset, bool graphs, int rounds,
                const std::string& what) {
  const auto size = static_cast<std::size_t>(group.size());
  std::vector<std::vector<HostF>> got(size);
  group.run([&](std::int64_t r) {
    cuda::Context ctx;
    ctx.policy().graphs = graphs;
    Dev<A> data = upload<A>(ctx, part_of<A>(n, r, 0), offset);
    const auto sum = group.shard(r);
    cuda::GraphCache graph;
    for (int round = 0; round < rounds; ++round) {
      const Dev<A> next = upload<A>(ctx, part_of<A>(n, r, round));
      cuda::copy(ctx, data, next);
      graph.run(ctx, {static_cast<std::uint64_t>(n)}, [&] { sum.sum(ctx, data.data(), n); });
      got[static_cast<std::size_t>(r)].push_back(download(ctx, data));
    }
    if (graphs) CHECK(graph.holds_collectives());
    CHECK(graph.captures() == (graphs ? 1 : 0));
  });
  for (int round = 0; round < rounds; ++round) {
    std::vector<HostF> parts;
    for (std::size_t r = 0; r < size; ++r) parts.push_back(part_of<A>(n, static_cast<std::int64_t>(r), round));
    const HostF want = expected_sum<A>(parts);
    for (std::size_t r = 0; r < size; ++r)
      CHECK_MESSAGE(count_bit_differences(got[r][static_cast<std::size_t>(round)], want) == 0, what, ": ", n,
                    " elements, offset ", offset, std::string(graphs ? ", graph" : ", direct"), ", round ", round, ", rank ", r);
  }
}

template <class A>
void check_group(cuda::PeerShardGroup<A>& group, const std::string& what) {
  // Whole packs, a remainder, fewer elements than blocks, more than the inboxes hold (capacity 4096).
  for (const std::int64_t n : {std::int64_t{1}, std::int64_t{8}, std::int64_t{1000}, std::int64_t{4099},
                               std::int64_t{3 * 4096 + 8}, std::int64_t{65536}})
    for (const bool graphs : {false, true}) check_sums<A>(group, n, 0, graphs, 3, what);
  check_sums<A>(group, 4104, 1, true, 3, what + ", misaligned");
}

}  // namespace

TEST_CASE_TEMPLATE("the peer group sums in rank order, rounded once, the same bits on every rank (one GPU)", A, float,
                   bf16) {
  EPONA_REQUIRE_GPU();
  Watchdog watchdog("the peer group's sums on one GPU", 300);
  for (const int shards : {2, 3, 4}) {
    cuda::PeerShardGroup<A> group(std::vector<int>(static_cast<std::size_t>(shards), 0),
                                  {.capacity = 4096, .blocks = 16, .share_devices = true});
    check_group(group, std::to_string(shards) + " shards on one GPU");
  }
  cuda::PeerShardGroup<A> one({0});  // a group of one leaves the buffer as it is
  check_sums<A>(one, 100, 0, false, 1, "one shard");
}

TEST_CASE_TEMPLATE("the peer group sums over two GPUs", A, float, bf16) {
  EPONA_REQUIRE_GPU();
  if (!two_gpus("the peer group over GPUs")) return;
  Watchdog watchdog("the peer group's sums over two GPUs", 300);
  cuda::PeerShardGroup<A> small({0, 1}, {.capacity = 4096, .blocks = 64});
  check_group(small, "2 GPUs");
  cuda::PeerShardGroup<A> real({0, 1});  // the default inboxes: a VisDiT block's output in one piece
  check_sums<A>(real, 1027 * 2048, 0, true, 3, "2 GPUs, one block's output");
}

TEST_CASE("the peer group refuses what it cannot do, by name") {
  EPONA_REQUIRE_GPU();
  int gpus = 0;
  EPONA_CUDA_CHECK(cudaGetDeviceCount(&gpus));
  using Group = cuda::PeerShardGroup<float>;
  CHECK_THROWS_WITH_AS(Group({0, 0}), doctest::Contains("device 0 twice"), Error);
  CHECK_THROWS_WITH_AS(Group({0, 99}), doctest::Contains("device 99 does not exist"), Error);
  CHECK_THROWS_WITH_AS(Group({}), doctest::Contains("0 devices"), Error);
  CHECK_THROWS_WITH_AS(Group({0}, {.capacity = 12}), doctest::Contains("capacity 12"), Error);
  CHECK_THROWS_WITH_AS(Group({0}, {.blocks = 0}), doctest::Contains("0 blocks"), Error);
  // Sums of different sizes: every rank stops with the error, none waits.
  Group uneven({0, 0}, {.share_devices = true});
  Dev<float> a({8}), b({8});
  CHECK_THROWS_WITH_AS(uneven.run([&](std::int64_t r) {
                         cuda::Context ctx;
                         uneven.shard(r).sum(ctx, (r == 0 ? a : b).data(), r + 4);
                       }),
                       doctest::Contains("different sizes"), Error);
  // A shard's sum on another GPU than its own.
  if (gpus >= 2) {
    Group pair({0, 1});
    CHECK_THROWS_WITH_AS(pair.run([&](std::int64_t r) {
                           cuda::Context ctx(0);
                           pair.shard(r).sum(ctx, a.data(), 8);
                         }),
                         doctest::Contains("its GPU is 1"), Error);
  }
}
