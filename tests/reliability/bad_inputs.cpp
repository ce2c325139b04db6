// Bad inputs that the readers' own tests do not already cover (docs/reliability.md maps every
// case of the reliability issue to its test): configuration FILES asking for absurd sizes
// (terabytes of activations, 10^12-wide layers, zero or fractional counts) are refused by
// parse_configs with the key named, before anything large is allocated (every allocation during
// the call is recorded by a replaced operator new); non-finite absolute poses and float32
// overflow in .npy pose files are refused with the file and row named.
#include <doctest/doctest.h>

#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <new>
#include <string>

#include <nlohmann/json.hpp>

#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/io/npy.hpp"
#include "../temp_dir.hpp"

using namespace epona;
using epona::test::TempDir;
using nlohmann::json;
namespace fs = std::filesystem;

// ---- the largest single allocation made while a check is running --------------------------
namespace {
std::atomic<bool> g_recording{false};
std::atomic<std::size_t> g_largest{0};

void* counted_alloc(std::size_t n, std::size_t align = alignof(std::max_align_t)) {
  if (g_recording.load(std::memory_order_relaxed)) {
    std::size_t seen = g_largest.load(std::memory_order_relaxed);
    while (n > seen && !g_largest.compare_exchange_weak(seen, n)) {
    }
  }
  if (n == 0) n = 1;
  return align <= alignof(std::max_align_t) ? std::malloc(n) : std::aligned_alloc(align, (n + align - 1) / align * align);
}
}  // namespace

void* operator new(std::size_t n) {
  if (void* p = counted_alloc(n)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return operator new(n); }
void* operator new(std::size_t n, const std::nothrow_t&) noexcept { return counted_alloc(n); }
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept { return counted_alloc(n); }
void* operator new(std::size_t n, std::align_val_t a) {
  if (void* p = counted_alloc(n, static_cast<std::size_t>(a))) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n, std::align_val_t a) { return operator new(n, a); }
void* operator new(std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
  return counted_alloc(n, static_cast<std::size_t>(a));
}
// Everything above allocates with malloc/aligned_alloc, so free is the matching release.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
#pragma GCC diagnostic pop

namespace {

// The message of the epona::Error that `f` throws, and the largest allocation it made.
template <class F>
std::string error_of(F&& f, std::size_t& largest_allocation) {
  std::string message = "(no error)";
  g_largest = 0;
  g_recording = true;
  try {
    f();
  } catch (const Error& e) {
    message = e.what();
  }
  g_recording = false;
  largest_allocation = g_largest;
  return message;
}

const json& golden_configs() {
  static const json j = [] {
    std::ifstream in(std::string(EPONA_TEST_DATA_DIR) + "/golden/configs.json");
    REQUIRE(in);
    return json::parse(in);
  }();
  return j;
}

constexpr std::size_t kSmallAllocation = 1 << 20;  // parsing a config needs far less than 1 MB at once

}  // namespace

TEST_CASE("config files asking for absurd sizes are refused by name before any large allocation") {
  struct Bad {
    const char* what;
    void (*edit)(json&);
    const char* message;
  };
  const Bad cases[] = {
      {"terabytes of activations", [](json& w) { w["image_size"] = {1 << 20, 1 << 20}; }, "of activations; the limit is"},
      {"a 10^12-wide MST", [](json& w) { w["n_embd"] = std::int64_t{1} << 40; }, "n_embd must be in [1, 16777216]"},
      {"10^11 parameters", [](json& w) { w["n_layer"] = {256, 1, 1}, w["n_embd"] = 8192, w["n_head"] = 64; },
       "the world model would have "},
      {"four million MST blocks", [](json& w) { w["n_layer"] = {4000000, 1, 1}; }, "n_layer[0] (MST blocks) must be in [1, 256]"},
      {"an int64-overflowing size", [](json& w) { w["n_embd_dit"] = 9223372036854775807.0 * 4; }, "n_embd_dit must be an integer"},
      {"a size past int64", [](json& w) { w["traj_len"] = std::uint64_t{1} << 63; }, "traj_len is out of range"},
      {"zero sampling steps", [](json& w) { w["num_sampling_steps"] = 0; }, "num_sampling_steps must be in [1,"},
      {"negative sampling steps", [](json& w) { w["num_sampling_steps"] = -5; }, "num_sampling_steps must be in [1,"},
      {"2^40 sampling steps", [](json& w) { w["num_sampling_steps"] = std::int64_t{1} << 40; }, "num_sampling_steps must be in [1, 100000]"},
      {"a fractional frame count", [](json& w) { w["condition_frames"] = 2.5; }, "condition_frames must be an integer"},
      {"more frames than the model has time embeddings", [](json& w) { w["condition_frames"] = 1000000; },
       "condition_frames must be in [1, 50]"},
      {"image size not a multiple of 32", [](json& w) { w["image_size"] = {64, 100}; }, "must be multiples of 32"},
      {"a zero image size", [](json& w) { w["image_size"] = {0, 128}; }, "image_size[0] (H) must be in [1,"},
  };
  for (const auto& bad : cases) {
    CAPTURE(bad.what);
    for (const bool golden_layout : {true, false}) {
      CAPTURE(golden_layout);
      json j = golden_layout ? json{{"world_model_config", golden_configs()["world_model_config"]},
                                    {"dcae", golden_configs()["dcae"]}}
                             : golden_configs()["world_model_config"];
      bad.edit(golden_layout ? j["world_model_config"] : j);
      const std::string text = j.dump();
      std::size_t largest = 0;
      const std::string msg = error_of([&] { (void)io::parse_configs(text, "bad.json"); }, largest);
      CHECK_MESSAGE(msg.find(bad.message) != std::string::npos, msg);
      CHECK(msg.rfind("bad.json: ", 0) == 0);
      CHECK(largest < kSmallAllocation);
    }
  }
}

TEST_CASE("a DC-AE section asking for absurd sizes is refused before any large allocation") {
  json j{{"world_model_config", golden_configs()["world_model_config"]}, {"dcae", golden_configs()["dcae"]}};
  auto& enc = j["dcae"]["config"]["encoder"];
  enc["width_list"] = {1 << 20, 1 << 20, 1 << 20, 1 << 20, 1 << 20, 1 << 20};
  std::size_t largest = 0;
  std::string msg = error_of([&] { (void)io::parse_configs(j.dump(), "bad.json"); }, largest);
  CHECK_MESSAGE(msg.find("the DC-AE would have ") != std::string::npos, msg);
  CHECK_MESSAGE(msg.find(" in fp32); the limit is ") != std::string::npos, msg);
  CHECK(largest < kSmallAllocation);

  j["dcae"] = golden_configs()["dcae"];  // the world model stays small: the DC-AE's own estimate refuses
  j["dcae"]["image_size"] = {1 << 18, 1 << 18};
  j["dcae"]["config"]["token_size"] = (1 << 13) * (1 << 13);
  msg = error_of([&] { (void)io::parse_configs(j.dump(), "bad.json"); }, largest);
  CHECK_MESSAGE(msg.find("one decode would need about ") != std::string::npos, msg);
  CHECK_MESSAGE(msg.find(" of activations; the limit is ") != std::string::npos, msg);
  CHECK(largest < kSmallAllocation);
}

TEST_CASE("non-finite and float32-overflowing poses in .npy files are refused with the row named") {
  TempDir dir;
  const double nan = std::numeric_limits<double>::quiet_NaN();
    // Absolute ego-to-world poses (N, 4, 4): identity, then a NaN translation, then an infinite rotation.
  Tensor<double> absolute = Tensor<double>::zeros({3, 4, 4});
  for (std::int64_t i = 0; i < 3; ++i)
    for (std::int64_t d = 0; d < 4; ++d) absolute.at(i, d, d) = 1.0;
  absolute.at(1, 0, 3) = nan;
  io::write_npy(dir.path / "absolute_nan.npy", absolute);
  CHECK_THROWS_WITH_AS(io::load_poses(dir.path / "absolute_nan.npy"),
                       doctest::Contains("absolute_nan.npy: get_rel_pose: from pose 0 to pose 1"), Error);
  CHECK_THROWS_WITH_AS(io::load_poses(dir.path / "absolute_nan.npy"), doctest::Contains("non-finite value (nan)"), Error);

  absolute.at(1, 0, 3) = 0.0;
  absolute.at(2, 0, 0) = std::numeric_limits<double>::infinity();
  io::write_npy(dir.path / "absolute_inf.npy", absolute);
  CHECK_THROWS_WITH_AS(io::load_poses(dir.path / "absolute_inf.npy"),
                       doctest::Contains("absolute_inf.npy: get_rel_pose: from pose 1 to pose 2"), Error);

  // (N, 3) rows in float64 whose value does not fit float32.
  Tensor<double> rows = Tensor<double>::zeros({2, 3});
  rows.at(1, 1) = 1e39;
  io::write_npy(dir.path / "rows.npy", rows);
  CHECK_THROWS_WITH_AS(io::load_poses(dir.path / "rows.npy"),
                       doctest::Contains("rows.npy: row 1: y = 1e+39 is not a finite number in float32"), Error);
}
