// Tests for epona/io/npy.hpp: files written by numpy itself (scripts/make_pose_fixtures.py),
// our writer read back, and hostile inputs (every one must end in epona::Error naming the problem).
#include <doctest/doctest.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "epona/io/npy.hpp"
#include "../bytes.hpp"

using namespace epona;
using epona::test::floats;
using epona::test::as_bytes;
namespace fs = std::filesystem;

namespace {

const fs::path kDir = fs::path(EPONA_TEST_DATA_DIR) / "poses" / "npy";

// A .npy file from parts: version, header text as given (no padding added), raw data bytes.
std::string make_npy(int major, const std::string& header, const std::string& data = {}) {
  std::string f = "\x93NUMPY";
  f += static_cast<char>(major);
  f += '\0';
  const std::size_t len_bytes = major == 1 ? 2 : 4;
  for (std::size_t i = 0; i < len_bytes; ++i) f += static_cast<char>((header.size() >> (8 * i)) & 0xff);
  return f + header + data;
}

template <class T = float>
io::NpyArray<T> parse(const std::string& file) {
  return io::parse_npy<T>(as_bytes(file), "test.npy");
}

fs::path temp_dir() {
  auto d = fs::temp_directory_path() / ("epona_npy_test_" + std::to_string(std::random_device{}()));
  fs::create_directories(d);
  return d;
}

}  // namespace

TEST_CASE("npy: files written by numpy (versions 1.0/2.0/3.0, f2/f4/f8)") {
  struct Case {
    const char* name;
    Shape shape;
    io::NpyDType dtype;
  };
  for (const Case& c : {Case{"f4_v1", {3, 4}, io::NpyDType::F32}, Case{"f8_v2", {3, 4}, io::NpyDType::F64},
                        Case{"f4_v3", {3, 2, 2}, io::NpyDType::F32}, Case{"f2_v1", {12}, io::NpyDType::F16}}) {
    CAPTURE(c.name);
    const auto a = io::read_npy<float>(kDir / (std::string(c.name) + ".npy"));
    CHECK(a.values.shape() == c.shape);
    CHECK(a.dtype == c.dtype);
    for (int i = 0; i < 12; ++i) CHECK(a.values.data()[i] == 0.25f * float(i) - 1.f);  // exact in f2/f4/f8
    const auto d = io::read_npy<double>(kDir / (std::string(c.name) + ".npy"));
    for (int i = 0; i < 12; ++i) CHECK(d.values.data()[i] == 0.25 * i - 1.0);
  }
  const auto s = io::read_npy(kDir / "scalar_f8.npy");
  CHECK(s.values.shape().empty());
  CHECK(s.values.numel() == 1);
  CHECK(s.values.data()[0] == 3.5f);
  const auto e = io::read_npy(kDir / "empty_f4.npy");
  CHECK(e.values.shape() == Shape{0, 2});
  CHECK(e.values.numel() == 0);
}

TEST_CASE("npy: unsupported kinds written by numpy are refused with a reason") {
  auto msg = [](const char* name) {
    try {
      io::read_npy(kDir / name);
    } catch (const Error& err) {
      return std::string(err.what());
    }
    return std::string("no error");
  };
  CHECK(msg("fortran_f4.npy").find("Fortran-order") != std::string::npos);
  CHECK(msg("bigendian_f4.npy").find("big-endian dtype '>f4'") != std::string::npos);
  CHECK(msg("int64.npy").find("unsupported dtype '<i8'") != std::string::npos);
  CHECK(msg("structured.npy").find("structured dtypes are not supported") != std::string::npos);
  CHECK(msg("int64.npy").find("int64.npy") != std::string::npos);  // names the file
  CHECK_THROWS_WITH_AS(io::read_npy(kDir / "missing.npy"), doctest::Contains("not found"), Error);
  CHECK_THROWS_WITH_AS(io::read_npy(kDir), doctest::Contains("not a regular file"), Error);
}

TEST_CASE("npy: header dialects numpy or Python 2 produce") {
  const std::string data = floats({1, 2});
  CHECK(parse(make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (2,), }    \n", data))
            .values.at(1) == 2.f);
  // other key order, double quotes, no trailing comma, Python 2 long suffix, tab/CR whitespace
  auto a = parse(make_npy(2, "{\"shape\": (1L, 2L), \"fortran_order\": False,\t\"descr\": \"<f4\"}\r\n", data));
  CHECK(a.values.shape() == Shape{1, 2});
  CHECK(parse(make_npy(3, "{'descr':'<f4','fortran_order':False,'shape':(2 , )}", data)).values.at(0) == 1.f);
}

TEST_CASE("npy: hostile or broken files end in a named error") {
  const std::string ok_header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2,), }\n";
  const std::string data = floats({1, 2});
  struct Case {
    std::string file;
    std::string expect;
  };
  const Case cases[] = {
      {"", "too short"},
      {"\x93NUMPY\x01", "too short"},
      {"PK\x03\x04" + std::string(60, 'x'), "bad magic"},
      {make_npy(4, ok_header, data), "unsupported .npy format version 4.0"},
      {make_npy(2, ok_header, data).substr(0, 11), "truncated .npy preamble"},
      {make_npy(1, ok_header, data).substr(0, 30), "runs past the end of the file"},
      {make_npy(2, std::string(2'000'000, ' ')), "implausibly large"},
      {make_npy(1, ok_header, data + "xx"), "needs 8 data bytes, the file has 10"},
      {make_npy(1, ok_header, data.substr(0, 5)), "needs 8 data bytes, the file has 5"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (4611686018427387904, 4)}", data),
       "is too large"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (999999999999999999999,)}", data),
       "dimension too large"},
      {make_npy(1, "{'descr': '<f8', 'fortran_order': False, 'shape': (3000000000000000000,)}", data),
       "too large"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (-2,)}", data),
       "expected a non-negative integer"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (2)}", data), "not a tuple"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': [2]}", data), "must be a tuple"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (2,), 'x': 1}", data),
       "unexpected key 'x'"},
      {make_npy(1, "{'descr': '<f4', 'shape': (2,)}", data), "missing key"},
      {make_npy(1, "{'descr': '<f4', 'descr': '<f4', 'fortran_order': False, 'shape': (2,)}", data),
       "duplicate key 'descr'"},
      {make_npy(1, "{'descr': '<f4, 'fortran_order': False, 'shape': (2,)}", data), "unsupported dtype '<f4, '"},
      {make_npy(1, "{'descr' '<f4', 'fortran_order': False, 'shape': (2,)}", data), "expected ':'"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (2,)", data), "header ends early"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (2,)}}", data), "after the closing"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': 0, 'shape': (2,)}", data), "True or False"},
      {make_npy(1, "{'descr': __import__('os').system('x'), 'fortran_order': False, 'shape': (2,)}", data),
       "must be a string"},
      {make_npy(1, "{'descr': '<f\\x34', 'fortran_order': False, 'shape': (2,)}", data), "escape"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': (2,), }\xc3\xa9", data), "non-ASCII"},
      {make_npy(1, std::string("{'descr': '<f4', 'fortran_order': False, 'shape': (2,)}") + '\0', data), "NUL"},
      {make_npy(1, "", data), "header ends early"},
      {make_npy(1, "{'descr': '<i4', 'fortran_order': False, 'shape': (2,)}", data), "unsupported dtype '<i4'"},
      {make_npy(1, "{'descr': '|b1', 'fortran_order': False, 'shape': (8,)}", data), "unsupported dtype '|b1'"},
      {make_npy(1, "{'descr': '<f4', 'fortran_order': True, 'shape': (2,)}", data), "Fortran-order"},
  };
  for (const auto& c : cases) {
    CAPTURE(c.expect);
    CHECK_THROWS_WITH_AS(parse(c.file), doctest::Contains(c.expect.c_str()), Error);
    CHECK_THROWS_WITH_AS(parse(c.file), doctest::Contains("test.npy"), Error);
  }
  std::string many_dims = "(";
  for (int i = 0; i < 65; ++i) many_dims += "1, ";
  CHECK_THROWS_WITH_AS(
      parse(make_npy(1, "{'descr': '<f4', 'fortran_order': False, 'shape': " + many_dims + ")}", data)),
      doctest::Contains("more than 64 dimensions"), Error);
}

TEST_CASE("npy: every truncation and random header corruption is an error or a valid array, never a crash") {
  const std::string good = io::to_npy_bytes(Tensor<float>::full({3, 5}, 0.5f));
  for (std::size_t n = 0; n < good.size(); ++n) CHECK_THROWS_AS(parse(good.substr(0, n)), Error);
  std::mt19937 gen(7);
  int parsed = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    std::string f = good;
    for (int k = 0; k < 3; ++k) f[gen() % f.size()] = static_cast<char>(gen() % 256);
    try {
      const auto a = parse(f);
      CHECK(a.values.numel() <= 30);  // the data size was checked against the file
      ++parsed;
    } catch (const Error&) {
    }
  }
  CHECK(parsed > 0);  // harmless flips (padding spaces) still parse
}

TEST_CASE("npy: writer output is numpy's layout and reads back exactly") {
  for (const Shape& shape : {Shape{}, Shape{5}, Shape{2, 3, 4}, Shape{0, 3}}) {
    CAPTURE(shape_str(shape));
    Tensor<float> t(shape);
    for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = std::ldexp(float(i) - 7.3f, int(i % 5) - 2);
    const std::string bytes = io::to_npy_bytes(t);
    CHECK(bytes.compare(0, 8, std::string("\x93NUMPY\x01\x00", 8)) == 0);
    const std::size_t hlen = std::uint8_t(bytes[8]) | std::size_t(std::uint8_t(bytes[9])) << 8;
    CHECK((10 + hlen) % 64 == 0);
    CHECK(bytes[10 + hlen - 1] == '\n');
    const auto back = parse(bytes);
    CHECK(back.dtype == io::NpyDType::F32);
    REQUIRE(back.values.shape() == shape);
    CHECK(std::memcmp(back.values.data(), t.data(), t.nbytes()) == 0);
  }
  Tensor<double> d({2, 2});
  for (int i = 0; i < 4; ++i) d.data()[i] = 1.0 / 3.0 + i;
  const auto back = parse<double>(io::to_npy_bytes(d));
  CHECK(back.dtype == io::NpyDType::F64);
  CHECK(back.values.at(1, 1) == 1.0 / 3.0 + 3);
}

TEST_CASE("npy: write_npy replaces files atomically and reports unwritable paths") {
  const fs::path dir = temp_dir();
  const fs::path file = dir / "latents.npy";
  io::write_npy(file, Tensor<float>::full({4}, 1.f));
  io::write_npy(file, Tensor<float>::full({2, 2}, 2.f));
  const auto a = io::read_npy(file);
  CHECK(a.values.shape() == Shape{2, 2});
  CHECK(a.values.at(1, 1) == 2.f);
  int entries = 0;
  for ([[maybe_unused]] auto& e : fs::directory_iterator(dir)) ++entries;
  CHECK(entries == 1);  // no temporary left behind
  CHECK_THROWS_WITH_AS(io::write_npy(dir / "no" / "such" / "dir.npy", a.values),
                       doctest::Contains("cannot create the temporary file"), Error);
  fs::remove_all(dir);
}
