// Weight binding of the world model: a missing, an unexpected and a mis-shaped key in a copy of
// the golden weights are all named in one epona::Error; a file without TrajDiT weights is
// refused (the official loader would keep random ones); bf16 weights bind and give the same
// model up to bf16 rounding.
#include <doctest/doctest.h>

#include <string>

#include "epona/model/random_weights.hpp"
#include "epona/model/world_model.hpp"
#include "../error_text.hpp"
#include "world_golden.hpp"

using namespace epona;
using epona::test::contains;
using epona::test::world_golden;

namespace {

// A copy of `src` without `drop`, with `reshape` flattened to 1-d, plus `extras`.
io::TensorMap modified(const io::TensorMap& src, const std::string& drop, const std::string& reshape,
                       const std::vector<std::string>& extras) {
  io::TensorMap m("modified weights");
  for (const auto& [name, raw] : src.entries()) {
    if (name == drop) continue;
    io::RawTensor r = raw;
    if (name == reshape) r.shape = {raw.numel()};
    m.add(name, r);
  }
  const io::RawTensor& any = src.entries().begin()->second;
  for (const auto& e : extras) m.add(e, any);
  return m;
}

std::string load_error(const io::TensorMap& w) {
  try {
    (void)WorldModel<Cpu, float>::load(w, world_golden().world());
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("the golden weights bind strictly, from a map and from the file") {
  CHECK_NOTHROW((void)WorldModel<Cpu, float>::load(world_golden().weights, world_golden().world()));
  CHECK_NOTHROW((void)WorldModel<Cpu, bf16>::load_file(test::golden_dir() + "/weights_world.safetensors",
                                                       world_golden().world()));
  // The DC-AE file has no world-model key at all: every one is reported missing.
  try {
    (void)WorldModel<Cpu, float>::load_file(test::golden_dir() + "/weights_dcae.safetensors", world_golden().world());
    FAIL("a DC-AE file must not load as a world model");
  } catch (const Error& e) {
    CHECK(contains(e.what(), "no TrajDiT weights"));
    CHECK(contains(e.what(), "missing 'module.model.time_emb'"));
  }
}

TEST_CASE("missing, unexpected and mis-shaped keys are all named at once") {
  const std::string dropped = "module.dit.single_blocks.0.linear2.bias";
  const std::string flattened = "module.model.causal_time_space_blocks.0.space_block.attn.key.weight";
  const std::string extra = "module.traj_dit.bogus.weight";
  const std::string msg = load_error(modified(world_golden().weights, dropped, flattened, {extra, "decoder.x"}));
  INFO(msg);
  CHECK(contains(msg, "missing '" + dropped + "'"));
  CHECK(contains(msg, "'" + flattened + "' has shape"));
  CHECK(contains(msg, "unexpected '" + extra + "'"));
  CHECK_FALSE(contains(msg, "decoder.x"));  // keys outside module.* (e.g. a merged DC-AE) are not ours
  CHECK(contains(msg, "3 weight problem(s)"));
}

TEST_CASE("each network binds from its own prefix") {
  // Every key of one network removed: all of them reported, nothing else.
  for (const std::string prefix : {"module.model.", "module.dit."}) {
    io::TensorMap m("without " + prefix);
    std::size_t removed = 0;
    for (const auto& [name, raw] : world_golden().weights.entries()) {
      if (name.rfind(prefix, 0) == 0) {
        ++removed;
        continue;
      }
      m.add(name, raw);
    }
    const std::string msg = load_error(m);
    INFO(msg);
    CHECK(contains(msg, std::to_string(removed) + " weight problem(s)"));
    CHECK(contains(msg, "missing '" + prefix));
  }
}

TEST_CASE("a checkpoint without TrajDiT weights is refused, not silently random") {
  io::TensorMap m("no trajdit");
  std::size_t traj_keys = 0;
  for (const auto& [name, raw] : world_golden().weights.entries()) {
    if (name.rfind("module.traj_dit.", 0) != 0) m.add(name, raw);
    else ++traj_keys;
  }
  const std::string msg = load_error(m);
  INFO(msg);
  CHECK(contains(msg, "no TrajDiT weights"));
  CHECK(contains(msg, std::to_string(traj_keys + 1) + " weight problem(s)"));  // the note + every TrajDiT key
  CHECK(contains(msg, "missing 'module.traj_dit."));
}

TEST_CASE("a config that does not match the weights is refused with the shapes named") {
  auto cfg = world_golden().world();
  cfg.n_embd *= 2;
  cfg.n_head *= 2;
  try {
    (void)WorldModel<Cpu, float>::load(world_golden().weights, cfg);
    FAIL("loading with a wrong n_embd must throw");
  } catch (const Error& e) {
    INFO(e.what());
    CHECK(contains(e.what(), "'module.model.time_emb' has shape"));
  }
}

TEST_CASE("random_world_weights has exactly the golden file's keys and shapes, and binds strictly") {
  const auto& g = world_golden();
  const auto random = model::random_world_weights(g.world(), 3);
  CHECK(random.size() == g.weights.size());
  for (const auto& [name, raw] : g.weights.entries()) {
    INFO(name);
    REQUIRE(random.contains(name));
    CHECK(random.at(name).shape == raw.shape);
  }
  CHECK_NOTHROW((void)WorldModel<Cpu, float>::load(random, g.world()));
}
