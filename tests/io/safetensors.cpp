// Tests for epona/io/safetensors.hpp and epona/io/mmap.hpp: the golden weight and case files
// load with exactly the names, shapes and dtypes listed in manifest.json; writing and reading
// back is lossless for every dtype; every hostile file (generated here in a temp dir) gives an
// epona::Error that names the file and the problem.
#include <doctest/doctest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <unistd.h>

#include "epona/io/safetensors.hpp"
#include "../golden_dir.hpp"
#include "../temp_dir.hpp"

using namespace epona;
using epona::test::TempDir;
using epona::test::golden_dir;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

const json& manifest() {
  static const json j = [] {
    std::ifstream in(golden_dir() + "/manifest.json");
    REQUIRE_MESSAGE(in, "cannot open manifest.json in " << golden_dir());
    return json::parse(in);
  }();
  return j;
}

DType dtype_from_manifest(const std::string& name) {
  if (name == "float32") return DType::F32;
  if (name == "bfloat16") return DType::BF16;
  if (name == "float16") return DType::F16;
  if (name == "int64") return DType::I64;
  FAIL("unknown manifest dtype " << name);
  return DType::F32;
}

// Manifest listings come as {name: shape}, {name: [shape, dtype]} or {name: {shape, dtype, ...}}.
struct Expected {
  Shape shape;
  DType dtype = DType::F32;  // the README: all float32 unless stated
};
Expected expected_of(const json& v) {
  Expected e;
  if (v.is_object()) {
    e.shape = v.at("shape").get<Shape>();
    if (v.contains("dtype")) e.dtype = dtype_from_manifest(v.at("dtype").get<std::string>());
  } else if (!v.empty() && v[0].is_array()) {
    e.shape = v[0].get<Shape>();
    if (v.size() > 1) e.dtype = dtype_from_manifest(v[1].get<std::string>());
  } else {
    e.shape = v.get<Shape>();
  }
  return e;
}

void check_against_manifest(const std::string& file, const json& listing) {
  CAPTURE(file);
  const auto f = io::read_safetensors(golden_dir() + "/" + file);
  CHECK(f.tensors.size() == listing.size());
  for (auto it = listing.begin(); it != listing.end(); ++it) {
    CAPTURE(it.key());
    REQUIRE(f.tensors.contains(it.key()));
    const auto& t = f.tensors.at(it.key());
    const Expected e = expected_of(*it);
    CHECK(t.shape == e.shape);
    CHECK(t.dtype == e.dtype);
    CHECK(t.bytes.size() == std::size_t(t.numel()) * dtype_size(t.dtype));
  }
  CHECK(f.metadata.at("set") == manifest().at("set").get<std::string>());
}

void write_bytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

std::string le64(std::uint64_t v) {
  std::string s(8, '\0');
  for (int i = 0; i < 8; ++i) s[std::size_t(i)] = char((v >> (8 * i)) & 0xff);
  return s;
}

// A safetensors image with this header text and `data_bytes` zero bytes of data.
std::string image(const std::string& header, std::size_t data_bytes) {
  return le64(header.size()) + header + std::string(data_bytes, '\0');
}

// The message of the epona::Error that reading `path` throws ("" if none).
std::string read_error(const std::string& path) {
  try {
    io::read_safetensors(path);
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

void check_refused(const TempDir& dir, const std::string& name, const std::string& bytes, const std::string& problem) {
  const std::string path = dir / name;
  write_bytes(path, bytes);
  const std::string msg = read_error(path);
  CAPTURE(name);
  CAPTURE(msg);
  CHECK(msg.find(path) != std::string::npos);
  CHECK(msg.find(problem) != std::string::npos);
}

}  // namespace

TEST_CASE("golden files: names, shapes and dtypes equal manifest.json") {
  check_against_manifest("weights_world.safetensors", manifest().at("weights_world"));
  check_against_manifest("weights_dcae.safetensors", manifest().at("weights_dcae"));
  check_against_manifest("cases.safetensors", manifest().at("tensors"));
}

TEST_CASE("golden file: tensors stay valid after the file handle is gone") {
  io::TensorMap m;
  {
    m = io::load_safetensors(golden_dir() + "/cases.safetensors");
  }
  const auto name = m.names().front();
  const auto t = io::to_tensor<float>(m.at(name));
  double sum = 0;
  for (std::int64_t i = 0; i < t.numel(); ++i) sum += std::abs(t.data()[i]);
  CHECK(std::isfinite(sum));
  const auto sub = m.with_prefix(name.substr(0, 3));
  CHECK(sub.size() >= 1);
}

TEST_CASE("write then read back: every dtype, scalars, empty tensors, metadata") {
  TempDir dir;
  auto f32 = Tensor<float>({2, 3});
  for (int i = 0; i < 6; ++i) f32.data()[i] = 0.1f * float(i) - 0.25f;
  auto b16 = Tensor<bf16>({5});
  for (int i = 0; i < 5; ++i) b16.data()[i] = bf16(float(i) * 1.5f);
  auto i64 = Tensor<std::int64_t>(Shape{});
  i64.data()[0] = -1234567890123;
  auto empty = Tensor<float>({0, 4});
  const std::vector<std::uint16_t> half = {0x3c00, 0xc000, 0x0001, 0x7bff};  // 1, -2, min subnormal, max
  io::TensorMap m;
  m.add("a.f32", io::raw_view(f32));
  m.add("b.bf16", io::raw_view(b16));
  m.add("c.i64_scalar", io::raw_view(i64));
  m.add("d.empty", io::raw_view(empty));
  m.add("e.f16", io::RawTensor{DType::F16, {2, 2},
                               std::span<const std::byte>(reinterpret_cast<const std::byte*>(half.data()), 8)});
  const io::SafetensorsMetadata meta = {{"producer", "epona test"}, {"seed", "7"}};
  const auto path = dir / "round.safetensors";
  io::save_safetensors(path, m, meta);
  CHECK_FALSE(fs::exists(path + ".tmp-" + std::to_string(::getpid())));

  const auto back = io::read_safetensors(path);
  CHECK(back.metadata == meta);
  REQUIRE(back.tensors.size() == m.size());
  for (const auto& [name, t] : m.entries()) {
    CAPTURE(name);
    const auto& r = back.tensors.at(name);
    CHECK(r.dtype == t.dtype);
    CHECK(r.shape == t.shape);
    REQUIRE(r.bytes.size() == t.bytes.size());
    CHECK(std::equal(r.bytes.begin(), r.bytes.end(), t.bytes.begin()));
  }
  const auto h = io::to_tensor<float>(back.tensors.at("e.f16"));
  CHECK(h.at(0, 0) == 1.0f);
  CHECK(h.at(0, 1) == -2.0f);
  CHECK(h.at(1, 0) == std::ldexp(1.0f, -24));
  CHECK(h.at(1, 1) == 65504.0f);
  // Data starts 8-byte aligned (header padded) and the header is plain JSON.
  std::ifstream in(path, std::ios::binary);
  std::string len(8, '\0');
  in.read(len.data(), 8);
  std::uint64_t n = 0;
  for (int i = 7; i >= 0; --i) n = (n << 8) | std::uint8_t(len[std::size_t(i)]);
  CHECK(n % 8 == 0);

  // A golden file re-saved reads back identical.
  const auto world = io::read_safetensors(golden_dir() + "/weights_world.safetensors");
  io::save_safetensors(dir / "world.safetensors", world.tensors, world.metadata);
  const auto again = io::read_safetensors(dir / "world.safetensors");
  CHECK(again.metadata == world.metadata);
  REQUIRE(again.tensors.size() == world.tensors.size());
  for (const auto& [name, t] : world.tensors.entries()) {
    const auto& r = again.tensors.at(name);
    CHECK((r.shape == t.shape && r.dtype == t.dtype &&
           std::equal(r.bytes.begin(), r.bytes.end(), t.bytes.begin(), t.bytes.end())));
  }
  // Overwriting an existing file replaces it.
  io::TensorMap one;
  one.add("x", io::raw_view(f32));
  io::save_safetensors(dir / "world.safetensors", one);
  CHECK(io::load_safetensors(dir / "world.safetensors").size() == 1);
}

TEST_CASE("writer refuses what it cannot write") {
  TempDir dir;
  auto t = Tensor<float>({1});
  io::TensorMap m;
  m.add("__metadata__", io::raw_view(t));
  CHECK_THROWS_WITH_AS(io::save_safetensors(dir / "meta.safetensors", m),
                       doctest::Contains("may not be named __metadata__"), Error);
  io::TensorMap ok;
  ok.add("x", io::raw_view(t));
  CHECK_THROWS_WITH_AS(io::save_safetensors(dir / "no/such/dir/x.safetensors", ok),
                       doctest::Contains("cannot create"), Error);
}

TEST_CASE("hostile files: each refused with the file and the problem named") {
  TempDir dir;
  const std::string f32_1 = R"("a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]})";

  SUBCASE("missing file") {
    const auto path = dir / "absent.safetensors";
    const auto msg = read_error(path);
    CHECK(msg.find(path) != std::string::npos);
    CHECK(msg.find("does not exist") != std::string::npos);
  }
  SUBCASE("directory instead of a file") {
    const auto msg = read_error(dir.path.string());
    CHECK(msg.find(dir.path.string()) != std::string::npos);
    CHECK(msg.find("is a directory") != std::string::npos);
  }
  SUBCASE("empty file") { check_refused(dir, "empty.safetensors", "", "empty file"); }
  SUBCASE("shorter than the length field") { check_refused(dir, "short.safetensors", "abc", "truncated"); }
  SUBCASE("header length past EOF") {
    check_refused(dir, "len.safetensors", le64(1000) + "{}", "header length 1000 runs past the end");
    check_refused(dir, "len2.safetensors", le64(~std::uint64_t{0}) + "{}", "runs past the end");
  }
  SUBCASE("header not JSON") { check_refused(dir, "nojson.safetensors", image("{\"a\": [1,", 0), "invalid JSON"); }
  SUBCASE("header binary garbage") {
    check_refused(dir, "garbage.safetensors", image(std::string("\xff\xfe\x00\x01", 4), 0), "invalid JSON");
  }
  SUBCASE("header not an object") {
    check_refused(dir, "array.safetensors", image("[1, 2]", 0), "header is not a JSON object");
  }
  SUBCASE("deeply nested header") {
    check_refused(dir, "deep.safetensors", image("{\"a\":" + std::string(100000, '[') + std::string(100000, ']') + "}", 0),
                  "nests deeper");
  }
  SUBCASE("entry not an object") { check_refused(dir, "entry.safetensors", image(R"({"a": 5})", 0), "must be an object"); }
  SUBCASE("missing dtype") {
    check_refused(dir, "nodtype.safetensors", image(R"({"a":{"shape":[1],"data_offsets":[0,4]}})", 4), "has no 'dtype'");
  }
  SUBCASE("unsupported dtype") {
    check_refused(dir, "f64.safetensors", image(R"({"a":{"dtype":"F64","shape":[1],"data_offsets":[0,8]}})", 8),
                  "dtype 'F64', which is not supported");
  }
  SUBCASE("negative dimension") {
    check_refused(dir, "neg.safetensors", image(R"({"a":{"dtype":"F32","shape":[-1],"data_offsets":[0,4]}})", 4),
                  "must be a non-negative integer");
  }
  SUBCASE("fractional dimension") {
    check_refused(dir, "frac.safetensors", image(R"({"a":{"dtype":"F32","shape":[1.5],"data_offsets":[0,4]}})", 4),
                  "must be a non-negative integer");
  }
  SUBCASE("absurd dimensions") {
    check_refused(dir, "huge.safetensors",
                  image(R"({"a":{"dtype":"F32","shape":[1000000000000],"data_offsets":[0,4]}})", 4),
                  "needs 1000000000000 elements of 4 bytes, its data_offsets span 4 bytes");
    check_refused(dir, "overflow.safetensors",
                  image(R"({"a":{"dtype":"F32","shape":[4294967296,4294967296],"data_offsets":[0,4]}})", 4),
                  "overflows");
  }
  SUBCASE("offsets past the data") {
    check_refused(dir, "past.safetensors", image(R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}})", 4),
                  "run past the end of the data section");
  }
  SUBCASE("offsets reversed") {
    check_refused(dir, "rev.safetensors", image(R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[4,0]}})", 8),
                  "end before they begin");
  }
  SUBCASE("offsets malformed") {
    check_refused(dir, "malformed.safetensors", image(R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0]}})", 4),
                  "data_offsets must be [begin, end]");
  }
  SUBCASE("size does not match the shape") {
    check_refused(dir, "size.safetensors", image(R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,8]}})", 8),
                  "needs 1 elements of 4 bytes, its data_offsets span 8 bytes");
  }
  SUBCASE("overlapping ranges") {
    check_refused(dir, "overlap.safetensors",
                  image(R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},)"
                        R"("b":{"dtype":"F32","shape":[2],"data_offsets":[4,12]}})", 12),
                  "overlap");
  }
  SUBCASE("duplicate names") {
    check_refused(dir, "dup.safetensors", image("{" + f32_1 + "," + f32_1 + "}", 4), "header: duplicate key 'a'");
  }
  SUBCASE("metadata not strings") {
    check_refused(dir, "meta.safetensors", image(R"({"__metadata__":{"seed":1},)" + f32_1 + "}", 4),
                  "__metadata__ value 'seed' must be a string");
    check_refused(dir, "meta2.safetensors", image(R"({"__metadata__":[1],)" + f32_1 + "}", 4),
                  "__metadata__ must be an object");
  }
  SUBCASE("truncated real file") {
    std::ifstream in(golden_dir() + "/weights_world.safetensors", std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    REQUIRE(bytes.size() > 1000);
    check_refused(dir, "cut_data.safetensors", bytes.substr(0, bytes.size() - 100), "run past the end of the data");
    check_refused(dir, "cut_header.safetensors", bytes.substr(0, 500), "runs past the end of the file");
  }
  SUBCASE("accepted: zero-size tensors may share an offset, metadata exposed") {
    const auto path = dir / "ok.safetensors";
    write_bytes(path, image(R"({"__metadata__":{"k":"v"},"z1":{"dtype":"BF16","shape":[0],"data_offsets":[0,0]},)"
                            R"("z2":{"dtype":"I64","shape":[3,0],"data_offsets":[0,0]},)" + f32_1 + "}", 4));
    const auto f = io::read_safetensors(path);
    CHECK(f.tensors.size() == 3);
    CHECK(f.metadata.at("k") == "v");
  }
}
