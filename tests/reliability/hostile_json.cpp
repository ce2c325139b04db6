// Issue #36, JSON: every JSON reader bounds the nesting depth while it parses and never walks a
// value recursively in an error. Each reader gets hundreds of thousands of '[' in-process: before
// the fix, dump() in the error path (or a recursive walk) overflowed the stack (SIGSEGV).
#include <doctest/doctest.h>

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>

#include "../temp_dir.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "epona/eval/clip_set.hpp"
#include "epona/io/json_reader.hpp"
#include "epona/io/safetensors.hpp"
#include "../error_text.hpp"

using namespace epona;
using epona::test::contains;

namespace {

constexpr std::size_t kDeep = 300'000;  // far beyond any stack a recursive walk could survive

std::string deep_list(std::size_t n, bool closed) {
  std::string s(n, '[');
  if (closed) s += std::string(n, ']');
  return s;
}

template <class F>
std::string error_of(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "(no error)";
}

// The deep value at the top, under the key each reader reads, and closed or left open.
std::vector<std::string> deep_documents(const std::string& key) {
  std::vector<std::string> out;
  for (bool closed : {false, true}) {
    out.push_back(deep_list(kDeep, closed));
    out.push_back("{\"" + key + "\": " + deep_list(kDeep, closed) + (closed ? "}" : ""));
  }
  return out;
}

}  // namespace

TEST_CASE("parse_json refuses nesting beyond the limit, counting linearly") {
  io::JsonWork work;
  const std::string e = error_of([&] { io::parse_json(deep_list(kDeep, true), "deep.json", {}, &work); });
  CHECK(contains(e, "deep.json: nests deeper than 64 levels"));
  CHECK(work.events <= 2 * std::uint64_t(io::limits::kJsonDepth));  // stopped at the limit, not at the end
  // Nesting at the limit is accepted.
  CHECK_NOTHROW(io::parse_json(deep_list(io::limits::kJsonDepth, true), "ok.json"));
}

TEST_CASE("parse_json: value count, string length, duplicate keys") {
  io::JsonLimits lim;
  lim.max_values = 100;
  std::string many = "[";
  for (int i = 0; i < 200; ++i) many += i ? ",1" : "1";
  many += "]";
  CHECK(contains(error_of([&] { io::parse_json(many, "many.json", lim); }), "more than 100 values"));
  lim = {};
  lim.max_string_bytes = 10;
  CHECK(contains(error_of([&] { io::parse_json("[\"" + std::string(50, 'a') + "\"]", "s.json", lim); }),
            "longer than the limit of 10 bytes"));
  CHECK(contains(error_of([&] { io::parse_json("{\"a\": 1, \"a\": 2}", "dup.json"); }), "duplicate key 'a'"));
  CHECK(contains(error_of([&] { io::parse_json("{\"a\": ", "cut.json"); }), "cut.json: invalid JSON"));
}

TEST_CASE("json_brief describes containers by size and escapes strings") {
  const auto deep = io::parse_json(deep_list(60, true), "x");
  CHECK(io::json_brief(deep) == "a list of 1 value(s)");
  CHECK(io::json_brief(nlohmann::json::object({{"a", 1}})) == "an object of 1 key(s)");
  CHECK(io::json_brief(nlohmann::json("a\x1b[2Jb")) == "\"a\\x1b[2Jb\"");
  CHECK(io::json_brief(nlohmann::json(std::string(1000, 'x'))).size() < 120);
  CHECK(io::json_brief(nlohmann::json(2.5)) == "2.5");
}

TEST_CASE("config JSON: deep nesting is refused, not a stack overflow") {
  for (const auto& doc : deep_documents("world_model_config"))
    CHECK(contains(error_of([&] { io::parse_configs(doc, "configs.json"); }), "nests deeper than"));
  // Within the limit, an error about a deep value describes it by size (dump() would walk it).
  const std::string e = error_of([&] { io::parse_configs("{\"world_model_config\": " + deep_list(50, true) + "}", "c.json"); });
  CHECK(contains(e, "must be a JSON object, got array a list of 1 value(s)"));
}

TEST_CASE("pose JSON: deep nesting is refused, not a stack overflow") {
  for (const auto& doc : deep_documents("poses"))
    CHECK(contains(error_of([&] { io::parse_pose_json(doc, "poses.json"); }), "poses.json: nests deeper than"));
  for (const auto& doc : deep_documents("absolute"))
    CHECK(contains(error_of([&] { io::parse_pose_json(doc, "poses.json"); }), "poses.json: nests deeper than"));
  const std::string e = error_of([&] { io::parse_pose_json("[[1, 2, " + deep_list(50, true) + "]]", "p.json"); });
  CHECK(contains(e, "yaw must be a number, got a list of 1 value(s)"));
}

TEST_CASE("trajectory JSON: deep nesting is refused, not a stack overflow") {
  for (const auto& doc : deep_documents("steps"))
    CHECK(contains(error_of([&] { io::parse_trajectory_json(doc, "traj.json"); }), "traj.json: nests deeper than"));
  const std::string e = error_of([&] { io::parse_trajectory_json("{\"steps\": [[" + deep_list(50, true) + "]]}", "t.json"); });
  CHECK(contains(e, "expected [x, y, yaw], got a list of 1 value(s)"));
  // read_actions sniffs a .json file with the same reader.
  test::TempDir dir;
  const auto path = dir.path / "actions.json";
  std::ofstream(path) << deep_list(kDeep, false);
  CHECK(contains(error_of([&] { io::read_actions(path); }), "nests deeper than"));
}

TEST_CASE("safetensors header: deep nesting is refused, not a stack overflow") {
  for (const auto& doc : deep_documents("w")) {
    std::string file(8, '\0');
    const std::uint64_t n = doc.size();
    std::memcpy(file.data(), &n, 8);  // little-endian hosts only, as the format
    file += doc;
    const std::span<const std::byte> bytes(reinterpret_cast<const std::byte*>(file.data()), file.size());
    CHECK(contains(error_of([&] { io::parse_safetensors(bytes, "m.safetensors", nullptr); }), "nests deeper than 3 levels"));
  }
}

TEST_CASE("boxes.json of an eval clip: deep nesting is refused, not a stack overflow") {
  test::TempDir dir;
  const auto path = dir.path / "boxes.json";
  std::ofstream(path) << "{\"ego\": " << deep_list(kDeep, true) << "}";
  CHECK(contains(error_of([&] { eval::read_boxes(path); }), "nests deeper than"));
}
