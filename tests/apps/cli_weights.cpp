// Tests of what issue #37 ("Real weights, documented") added to the `epona` program, run
// in-process with captured stdout/stderr: `info --sha256` / `--expect-sha256` (the check of a
// download against the digest its publisher lists) and `convert --dtype` (bfloat16 halves a
// float32 checkpoint; float16 refuses values beyond its range; integer tensors are kept).
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "../../apps/epona/cli.hpp"
#include "../temp_dir.hpp"
#include "cli_testing.hpp"
#include "epona/io/image.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/npy.hpp"
#include "epona/io/safetensors.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::check_cli_error;
using epona::test::write_file;
using epona::test::TempDir;
using test::cli;
using test::has;

namespace {

// "hello epona\n": its SHA-256 as `sha256sum` prints it.
const std::string kHello = "hello epona\n";
const std::string kHelloSha = "0f3395c6e780e2a1e17ea364718c0c1e9649cce7c1c1e6a1cad53e6b9e1f676a";

std::span<const std::byte> bytes_of(const std::vector<float>& v) {
  return {reinterpret_cast<const std::byte*>(v.data()), v.size() * sizeof(float)};
}

// A small float32 checkpoint: two float tensors (with ties of bf16 rounding, negatives, values
// far beyond float16's range) and BatchNorm's int64 counter.
struct SmallCheckpoint {
  std::vector<float> weight, bias;
  std::vector<std::int64_t> counter{7};
  io::TensorMap map;
  explicit SmallCheckpoint(float big) {
    for (int i = 0; i < 40; ++i) weight.push_back(std::ldexp(1.0f + float(i) * std::ldexp(1.0f, -9), i % 7 - 3) * (i % 3 ? 1 : -1));
    weight.push_back(1.0f + std::ldexp(1.0f, -8));      // halfway between two bf16 values: to even
    weight.push_back(1.0f + 3 * std::ldexp(1.0f, -8));  // halfway: up to even
    bias = {0.0f, -0.0f, 1e-30f, big, 3.14159265f};
    map.add("block.weight", {DType::F32, {6, 7}, bytes_of(weight)});
    map.add("block.bias", {DType::F32, {5}, bytes_of(bias)});
    map.add("bn.num_batches_tracked",
            {DType::I64, {1}, {reinterpret_cast<const std::byte*>(counter.data()), sizeof(std::int64_t)}});
  }
};

std::uint16_t bits16(const io::RawTensor& t, std::size_t i) {
  std::uint16_t b;
  std::memcpy(&b, t.bytes.data() + 2 * i, 2);
  return b;
}

}  // namespace

TEST_CASE("info --sha256: the digest of a small file, as sha256sum prints it, and its size") {
  TempDir t;
  write_file(t / "hello.txt", kHello);
  const auto r = cli({"info", "--sha256", t / "hello.txt"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, kHelloSha + "  " + (t / "hello.txt") + "  12 bytes"));
  CHECK_FALSE(has(r.out, "tensors:"));  // the tensors are not read: any file can be checked
}

TEST_CASE("info --expect-sha256: equal is quiet with a note, different fails naming both digests") {
  TempDir t;
  write_file(t / "hello.txt", kHello);
  auto r = cli({"info", t / "hello.txt", "--expect-sha256", kHelloSha});
  CHECK(r.rc == 0);
  CHECK(has(r.err, "matches"));
  std::string upper = kHelloSha;
  for (auto& c : upper) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  CHECK(cli({"info", t / "hello.txt", "--expect-sha256", upper, "-q"}).rc == 0);  // case does not matter

  const std::string other(64, 'a');
  r = cli({"info", t / "hello.txt", "--expect-sha256", other});
  check_cli_error(r, "SHA-256 mismatch");
  CHECK(has(r.err, kHelloSha));
  CHECK(has(r.err, other));
}

TEST_CASE("info --expect-sha256: a malformed digest is refused before any hashing") {
  TempDir t;
  write_file(t / "hello.txt", kHello);
  // The file does not exist: the digest is refused first, so the error is about the digest.
  check_cli_error(cli({"info", t / "absent.pkl", "--expect-sha256", "abc"}), "64 hex digits");
  check_cli_error(cli({"info", t / "hello.txt", "--expect-sha256", kHelloSha.substr(1)}), "64 hex digits");
  check_cli_error(cli({"info", t / "hello.txt", "--expect-sha256", kHelloSha.substr(1) + "g"}), "64 hex digits");
  check_cli_error(cli({"info", t / "hello.txt", t / "hello.txt", "--expect-sha256", kHelloSha}), "checks one file");
  check_cli_error(cli({"info", "--sha256", t / "absent.pkl"}), "no such file");
  check_cli_error(cli({"info", "--sha256", t / "hello.txt", "--write-config", t / "c.json"}),
              "--write-config describes the tensors");
}

TEST_CASE("--help of info and convert lists the options of issue #37") {
  const auto info = cli({"info", "--help"});
  CHECK(has(info.out, "--sha256"));
  CHECK(has(info.out, "--expect-sha256 HEX"));
  const auto convert = cli({"convert", "--help"});
  CHECK(has(convert.out, "--dtype TYPE"));
  CHECK(has(convert.out, "bfloat16"));
}

TEST_CASE("convert --dtype bfloat16: float tensors halved, rounded as the library rounds, ints kept") {
  TempDir t;
  const SmallCheckpoint ck(1e30f);
  io::save_safetensors(t / "small.safetensors", ck.map);
  const auto r = cli({"convert", t / "small.safetensors", t / "small-bf16.safetensors", "--dtype", "bfloat16", "-q"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  const auto file = io::read_safetensors(t / "small-bf16.safetensors");
  for (const auto* name : {"block.weight", "block.bias"}) {
    INFO(name);
    const auto& a = ck.map.at(name);
    const auto& b = file.tensors.at(name);
    CHECK(b.dtype == DType::BF16);
    CHECK(b.shape == a.shape);
    CHECK(b.bytes.size() * 2 == a.bytes.size());
    for (std::size_t i = 0; i < static_cast<std::size_t>(a.numel()); ++i)
      CHECK(bits16(b, i) == bf16::from_float(load_as_float(a.bytes.data(), DType::F32, i)));
  }
  CHECK(bits16(file.tensors.at("block.weight"), 40) == 0x3f80);  // ties to even
  CHECK(bits16(file.tensors.at("block.weight"), 41) == 0x3f82);
  const auto& counter = file.tensors.at("bn.num_batches_tracked");
  CHECK(counter.dtype == DType::I64);
  CHECK(std::memcmp(counter.bytes.data(), ck.counter.data(), 8) == 0);
  CHECK(file.metadata.at("dtype") == "bfloat16");
  CHECK(has(file.metadata.at("dtype_conversion"), "2 floating-point tensor(s) rounded to nearest even to bfloat16 from float32"));
  CHECK(has(file.metadata.at("dtype_conversion"), "1 integer tensor(s) kept"));
  CHECK(file.metadata.at("converted_from") == "small.safetensors");
  CHECK(io::load_weights(t / "small-bf16.safetensors").size() == 3);

  // Back to float32: exact (every bfloat16 is a float32), the ints still kept.
  REQUIRE(cli({"convert", t / "small-bf16.safetensors", t / "back.safetensors", "--dtype", "float32", "-q"}).rc == 0);
  const auto back = io::read_safetensors(t / "back.safetensors");
  const auto& w = back.tensors.at("block.weight");
  CHECK(w.dtype == DType::F32);
  for (std::size_t i = 0; i < ck.weight.size(); ++i)
    CHECK(load_as_float(w.bytes.data(), DType::F32, i) == bf16::to_float(bits16(file.tensors.at("block.weight"), i)));
  CHECK(back.tensors.at("bn.num_batches_tracked").dtype == DType::I64);
}

TEST_CASE("convert --dtype float16: rounded to nearest even; a finite value beyond its range is refused") {
  TempDir t;
  const SmallCheckpoint fits(60000.0f);
  io::save_safetensors(t / "fits.safetensors", fits.map);
  REQUIRE(cli({"convert", t / "fits.safetensors", t / "fits-fp16.safetensors", "--dtype", "float16", "-q"}).rc == 0);
  const auto file = io::read_safetensors(t / "fits-fp16.safetensors");
  const auto& b = file.tensors.at("block.bias");
  CHECK(b.dtype == DType::F16);
  for (std::size_t i = 0; i < fits.bias.size(); ++i) CHECK(bits16(b, i) == float_to_half(fits.bias[i]));

  const SmallCheckpoint big(70000.0f);
  io::save_safetensors(t / "big.safetensors", big.map);
  const auto r = cli({"convert", t / "big.safetensors", t / "big-fp16.safetensors", "--dtype", "float16"});
  check_cli_error(r, "tensor 'block.bias' holds 70000");
  CHECK(has(r.err, "beyond float16's range"));
  CHECK_FALSE(fs::exists(t / "big-fp16.safetensors"));  // written atomically: nothing left behind
  // bfloat16 has float32's range: the same file converts.
  CHECK(cli({"convert", t / "big.safetensors", t / "big-bf16.safetensors", "--dtype", "bf16", "-q"}).rc == 0);
}

TEST_CASE("convert --dtype: an unknown type is refused naming the allowed ones, before reading") {
  TempDir t;
  const auto r = cli({"convert", t / "absent.pkl", t / "out.safetensors", "--dtype", "int8"});
  check_cli_error(r, "--dtype must be one of bfloat16, bf16, float16, fp16, float32, fp32; got 'int8'");
}

TEST_CASE("convert --dtype bfloat16 of the golden DC-AE binds and encodes close to the original") {
  // The converted file must bind (same names and shapes). Its latents are close to, not equal to,
  // the original's under --dtype bfloat16: that engine rounds the weight matrices to bfloat16 as
  // convert does, but keeps norms, BatchNorm statistics and biases in float32 (docs/dcae.md),
  // which the converted file holds rounded.
  TempDir t;
  const std::string golden = EPONA_GOLDEN_DEFAULT_DIR;
  const std::string original = golden + "/weights_dcae.safetensors";
  REQUIRE(cli({"convert", original, t / "dcae-bf16.safetensors", "--dtype", "bfloat16", "-q"}).rc == 0);
  const std::string frame = std::string(EPONA_TEST_DATA_DIR) + "/demo/frame_01.png";
  auto run = [&](const std::string& weights, const std::string& dtype, const std::string& out) {
    return cli({"encode", frame, "-o", t / out, "--dcae", weights, "--config", golden + "/configs.json", "--dtype",
                dtype, "-q"});
  };
  const auto a = run(original, "bfloat16", "a.npy");
  INFO(a.err);
  REQUIRE(a.rc == 0);
  const auto b = run(t / "dcae-bf16.safetensors", "bfloat16", "b.npy");
  INFO(b.err);
  REQUIRE(b.rc == 0);
  const auto za = io::read_npy<float>(t / "a.npy").values, zb = io::read_npy<float>(t / "b.npy").values;
  REQUIRE(za.shape() == zb.shape());
  double max_diff = 0, max_abs = 0;
  for (std::int64_t i = 0; i < za.numel(); ++i) {
    max_diff = std::max(max_diff, double(std::fabs(za.data()[i] - zb.data()[i])));
    max_abs = std::max(max_abs, double(std::fabs(za.data()[i])));
  }
  MESSAGE("golden DC-AE latents, converted bf16 file vs original under --dtype bfloat16: max |diff| ", max_diff,
          " of max |z| ", max_abs);
  CHECK(max_diff <= 0.02 * max_abs);  // measured: 0.0037 of max |z|
  CHECK(run(t / "dcae-bf16.safetensors", "float32", "c.npy").rc == 0);  // and float32 reads it, widened exactly
}

// stb is compiled once per program (header-only), here.
#include "epona/io/stb_implementation.hpp"
