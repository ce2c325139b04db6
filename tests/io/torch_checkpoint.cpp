// Tests for epona/io/pickle.hpp, epona/io/torch_checkpoint.hpp and epona/io/load_weights.hpp:
// every fixture written by torch.save (scripts/make_pkl_fixtures.py) loads with the keys, dtypes,
// shapes and exact element bits that the script recorded; the converted golden weights equal the
// golden safetensors tensor for tensor; and hostile pickles and archives built here (dangerous
// globals, bad storages, deep nesting, memo abuse, absurd lengths, truncation) each fail with an
// epona::Error that names the problem.
#include "epona/io/torch_checkpoint.hpp"

#include <doctest/doctest.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "epona/io/load_weights.hpp"
#include "epona/io/pickle.hpp"
#include "epona/io/safetensors.hpp"
#include "zip_builder.hpp"
#include "../bytes.hpp"

using namespace epona;
using epona::test::floats;
using namespace epona::io;
using zip_test::put;
using namespace std::string_literals;

namespace {

const std::string kPklDir = std::string(EPONA_TEST_DATA_DIR) + "/pkl/";
const std::string kGoldenDir = std::string(EPONA_TEST_DATA_DIR) + "/golden/";

// ---- expected.txt: file, key, dtype, [shape], element bits ------------------------------------

struct ExpectedTensor {
  std::string dtype;
  Shape shape;
  std::vector<std::string> values;  // hex bits (floats) or decimal (int64)
};

std::map<std::string, std::map<std::string, ExpectedTensor>> read_expected() {
  std::ifstream in(kPklDir + "expected.txt");
  REQUIRE(in.good());
  std::map<std::string, std::map<std::string, ExpectedTensor>> out;
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    std::vector<std::string> f;
    std::stringstream ss(line);
    for (std::string field; std::getline(ss, field, '\t');) f.push_back(field);
    REQUIRE(f.size() >= 4);
    ExpectedTensor e;
    e.dtype = f[2];
    std::string dims = f[3].substr(1, f[3].size() - 2);
    std::stringstream ds(dims);
    for (std::string d; std::getline(ds, d, ',');) e.shape.push_back(std::stoll(d));
    if (f.size() > 4) {
      std::stringstream vs(f[4]);
      for (std::string v; vs >> v;) e.values.push_back(v);
    }
    out[f[0]][f[1]] = e;
  }
  return out;
}

// The same text encoding of a raw tensor's elements as the fixture script writes.
std::vector<std::string> element_bits(const RawTensor& t) {
  std::vector<std::string> v;
  const auto n = static_cast<std::size_t>(t.numel());
  const auto esize = dtype_size(t.dtype);
  for (std::size_t i = 0; i < n; ++i) {
    const std::byte* p = t.bytes.data() + i * esize;
    char buf[32];
    if (t.dtype == DType::I64) {
      std::int64_t x;
      std::memcpy(&x, p, 8);
      std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(x));
    } else if (esize == 4) {
      std::uint32_t x;
      std::memcpy(&x, p, 4);
      std::snprintf(buf, sizeof buf, "%08x", x);
    } else {
      std::uint16_t x;
      std::memcpy(&x, p, 2);
      std::snprintf(buf, sizeof buf, "%04x", x);
    }
    v.emplace_back(buf);
  }
  return v;
}

void check_against_expected(const TensorMap& map, const std::map<std::string, ExpectedTensor>& expected,
                            const std::string& file) {
  CHECK_MESSAGE(map.size() == expected.size(), file);
  for (const auto& [key, e] : expected) {
    INFO(file, " / ", key);
    REQUIRE(map.contains(key));
    const RawTensor& t = map.at(key);
    CHECK(std::string(dtype_name(t.dtype)) == e.dtype);
    CHECK(t.shape == e.shape);
    CHECK(element_bits(t) == e.values);
  }
}

// Expects `f` to throw epona::Error whose message contains every word.
template <class F>
void expect_error(F&& f, std::initializer_list<std::string> words) {
  try {
    f();
    FAIL("no error; expected one containing '", *words.begin(), "'");
  } catch (const Error& e) {
    const std::string msg = e.what();
    for (const auto& w : words) CHECK_MESSAGE(msg.find(w) != std::string::npos, "'", w, "' not in: ", msg);
  }
}

// ---- a tiny pickle writer for hand-made (hostile) checkpoints --------------------------------

struct PickleWriter {
  std::string b = "\x80\x02";
  PickleWriter& raw(std::string_view s) {
    b += s;
    return *this;
  }
  PickleWriter& str(std::string_view s) {
    b += 'X';
    put<std::uint32_t>(b, static_cast<std::uint32_t>(s.size()));
    b += s;
    return *this;
  }
  PickleWriter& integer(std::int64_t v) {
    if (v >= 0 && v < 256) {
      b += 'K';
      b += char(v);
    } else if (v >= INT32_MIN && v <= INT32_MAX) {
      b += 'J';
      put<std::int32_t>(b, static_cast<std::int32_t>(v));
    } else {
      b += "\x8a\x08";
      put<std::int64_t>(b, v);
    }
    return *this;
  }
  PickleWriter& global(std::string_view module, std::string_view name) {
    b += 'c';
    b += std::string(module) + "\n" + std::string(name) + "\n";
    return *this;
  }
  PickleWriter& int_tuple(const std::vector<std::int64_t>& v) {
    b += '(';
    for (auto x : v) integer(x);
    b += 't';
    return *this;
  }
  std::string done() const { return b + "."; }
};

struct FakeTensor {
  std::string name;
  std::vector<std::int64_t> shape, stride;
  std::int64_t offset = 0;
  std::string key = "0";
  std::int64_t numel = -1;  // declared storage numel; default: offset + numel(shape)
  std::string storage_type = "FloatStorage";
};

// One entry `name: tensor` of a state dict, exactly as torch.save pickles it.
void write_tensor(PickleWriter& p, const FakeTensor& t) {
  std::int64_t numel = t.numel;
  if (numel < 0) {  // default: exactly what the tensor needs (tests with huge shapes set it)
    numel = t.offset;
    std::int64_t n = 1;
    for (auto d : t.shape) n *= d;
    numel += n;
  }
  p.str(t.name).global("torch._utils", "_rebuild_tensor_v2").raw("((");
  p.str("storage").global("torch", t.storage_type).str(t.key).str("cpu").integer(numel);
  p.raw("tQ").integer(t.offset).int_tuple(t.shape).int_tuple(t.stride);
  p.raw("\x89").global("collections", "OrderedDict").raw(")Rt").raw("R");
}

std::string state_dict_pickle(const std::vector<FakeTensor>& tensors) {
  PickleWriter p;
  p.raw("}(");
  for (const auto& t : tensors) write_tensor(p, t);
  return p.raw("u").done();
}

// A torch.save-like archive: data.pkl, storage records, version (data descriptors as PyTorch).
std::string archive(const std::string& pickle, const std::map<std::string, std::string>& storages,
                    const std::string& prefix = "arc/") {
  zip_test::ZipSpec s;
  s.entries.push_back({prefix + "data.pkl", pickle});
  for (const auto& [k, v] : storages) s.entries.push_back({prefix + "data/" + k, v});
  s.entries.push_back({prefix + "version", "3\n"});
  for (auto& e : s.entries) e.descriptor = true;
  return zip_test::layout_zip(s).bytes();
}

TensorMap load_bytes(const std::string& bytes, const TorchLoadOptions& options = {}) {
  return load_torch_checkpoint(zip_test::open_zip(bytes, "hostile.pkl"), options);
}

void expect_load_error(const std::string& bytes, std::initializer_list<std::string> words) {
  expect_error([&] { load_bytes(bytes); }, words);
}

void expect_pickle_error(const std::string& pickle, std::initializer_list<std::string> words) {
  expect_load_error(archive(pickle, {{"0", floats({1, 2, 3, 4, 5, 6})}}), words);
}

}  // namespace

// ---- fixtures written by torch.save ------------------------------------------------------------

TEST_CASE("every torch.save fixture loads with the recorded keys, dtypes, shapes and bits") {
  const auto expected = read_expected();
  REQUIRE(expected.size() >= 7);
  for (const auto& [file, tensors] : expected) {
    const TensorMap map = load_torch_checkpoint(kPklDir + file);
    check_against_expected(map, tensors, file);
    CHECK(map.source() == kPklDir + file);
    check_against_expected(load_weights(kPklDir + file), tensors, file + " via load_weights");
  }
}

TEST_CASE("state dict selection: top level, model_state_dict, model, explicit key") {
  const auto expected = read_expected();
  // {"model_state_dict": ..., "epoch": 7, "lr": 1e-4, "note": ..., "flags": [...], "betas": (...)}
  const auto world = load_torch_checkpoint(kPklDir + "bf16_world.pkl", "model_state_dict");
  check_against_expected(world, expected.at("bf16_world.pkl"), "bf16_world.pkl explicit key");
  CHECK(world.contains("module.traj_dit.final_layer.linear.weight"));
  expect_error([] { load_torch_checkpoint(kPklDir + "bf16_world.pkl", "epoch"); },
               {"bf16_world.pkl", "'epoch' holds a int 7", "expected a dict of tensors"});
  expect_error(
      [] { load_torch_checkpoint(kPklDir + "bf16_world.pkl", "optimizer"); },
      {"no key 'optimizer'", "'model_state_dict' (dict of 5 items)", "'lr' (float", "'flags' (list of 3"});
  // {"model": OrderedDict (with _metadata, pickled via BUILD), "step": 20000}
  check_against_expected(load_torch_checkpoint(kPklDir + "fp16_dcae.pkl", "model"), expected.at("fp16_dcae.pkl"),
                         "fp16_dcae.pkl explicit key");
  expect_error([] { load_torch_checkpoint(kPklDir + "no_state_dict.pkl"); },
               {"no_state_dict.pkl", "no state dict found", "'epoch' (int 3)", "'config' (dict of 2 items)",
                "'model' (str 'dcae')"});
  expect_error([] { load_weights(kPklDir + "fp32_plain.pkl", "model"); }, {"no key 'model'", "'linear.weight'"});
}

TEST_CASE("tensors are zero-copy views; shared storages and offsets resolve into one record") {
  const auto map = load_torch_checkpoint(kPklDir + "views.pkl");
  const auto& base = map.at("base");
  CHECK(map.at("alias").bytes.data() == base.bytes.data());
  CHECK(map.at("slice").bytes.data() == base.bytes.data() + 10 * 4);
  CHECK(map.at("window").bytes.data() == base.bytes.data() + 30 * 4);
  CHECK(map.at("element").bytes.data() == base.bytes.data() + 5 * 4);
  CHECK(map.at("unit_dims").bytes.data() == map.at("rows").bytes.data() - 4 * 4);
  // Views stay valid after the map is copied and the original destroyed (the mapping is shared).
  TensorMap copy = map.with_prefix("param.");
  CHECK(copy.contains("weight"));
  const auto w = to_tensor<float>(copy.at("weight"));
  CHECK(w.shape() == Shape{2, 4});
}

TEST_CASE("converted golden weights equal the golden safetensors tensor for tensor") {
  for (const auto& [pkl, st] : {std::pair{"weights_world.pkl", "weights_world.safetensors"},
                                std::pair{"weights_dcae.pkl", "weights_dcae.safetensors"}}) {
    const auto t0 = std::chrono::steady_clock::now();
    const TensorMap a = load_weights(kPklDir + pkl);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    const TensorMap b = load_weights(kGoldenDir + st);
    MESSAGE(std::string(pkl), ": ", a.size(), " tensors loaded in ", ms, " ms");
    REQUIRE(a.names() == b.names());
    for (const auto& name : a.names()) {
      INFO(pkl, " / ", name);
      const auto &x = a.at(name), &y = b.at(name);
      CHECK(x.dtype == y.dtype);
      CHECK(x.shape == y.shape);
      REQUIRE(x.bytes.size() == y.bytes.size());
      CHECK(std::memcmp(x.bytes.data(), y.bytes.data(), x.bytes.size()) == 0);
    }
  }
  // The world-model file is found under "model_state_dict", the DC-AE under "model".
  CHECK(load_torch_checkpoint(kPklDir + "weights_world.pkl").contains("module.dit.img_in.weight"));
}

TEST_CASE("refused fixtures: non-contiguous tensor, os.system, legacy format") {
  expect_error([] { load_torch_checkpoint(kPklDir + "noncontiguous.pkl"); },
               {"noncontiguous.pkl", "tensor 'transposed'", "is not contiguous", "(1, 4)"});
  expect_error([] { load_weights(kPklDir + "hostile_os_system.pkl"); },
               {"hostile_os_system.pkl", "refusing to load: the pickle asks for global 'os.system'"});
  const auto legacy = (std::filesystem::temp_directory_path() / "epona_legacy_test.pt").string();
  {
    std::ofstream out(legacy, std::ios::binary);
    out << std::string("\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19.", 15);
  }
  expect_error([&] { load_weights(legacy); }, {"legacy (pre-PyTorch-1.6) torch.save file"});
  std::filesystem::remove(legacy);
  expect_error([] { load_weights(kPklDir + "missing.pkl"); }, {"missing.pkl", "cannot open"});
}

// ---- hand-made checkpoints ----------------------------------------------------------------------

TEST_CASE("hand-made checkpoint: offsets, strides of size-1 dims, empty tensors, dtypes") {
  std::string f16, i64;
  put<std::uint16_t>(f16, 0x3c00);
  put<std::uint16_t>(f16, 0xc000);
  put<std::int64_t>(i64, -5);
  const std::string pkl = state_dict_pickle({{"a", {2, 2}, {2, 1}, 1},
                                             {"col", {3, 1}, {1, 7}, 0},  // a size-1 dim: any stride
                                             {"none", {0, 4}, {4, 1}, 0},
                                             {"h", {2}, {1}, 0, "1", -1, "HalfStorage"},
                                             {"n", {}, {}, 0, "2", -1, "LongStorage"}});
  const std::string bytes = archive(pkl, {{"0", floats({9, 1, 2, 3, 4})}, {"1", f16}, {"2", i64}});
  const auto map = load_bytes(bytes);
  CHECK(map.size() == 5);
  const auto a = to_tensor<float>(map.at("a"));
  CHECK(a.at(0, 0) == 1.f);
  CHECK(a.at(1, 1) == 4.f);
  CHECK(to_tensor<float>(map.at("col")).at(2, 0) == 2.f);
  CHECK(map.at("none").numel() == 0);
  CHECK(map.at("h").dtype == DType::F16);
  CHECK(to_tensor<float>(map.at("h")).at(1) == -2.f);
  CHECK(map.at("n").dtype == DType::I64);
  CHECK(map.at("n").shape.empty());
  // Checksums: verified on request; a flipped storage byte is then caught.
  std::string corrupt = bytes;
  const auto pos = corrupt.find(floats({9, 1}));
  corrupt[pos + 5] ^= 0x40;
  CHECK_NOTHROW(load_bytes(corrupt));
  expect_error([&] { load_bytes(corrupt, {.key = "", .verify_checksums = true}); },
               {"entry 'arc/data/0' is corrupt: CRC-32"});
  CHECK_NOTHROW(load_bytes(bytes, {.key = "", .verify_checksums = true}));
}

TEST_CASE("hostile globals are refused by name, never resolved") {
  for (const auto& [module, name] : {std::pair{"os", "system"},
                                     {"posix", "system"},
                                     {"builtins", "eval"},
                                     {"builtins", "exec"},
                                     {"subprocess", "Popen"},
                                     {"torch", "load"},
                                     {"torch._utils", "_rebuild_qtensor"},
                                     {"collections", "namedtuple"},
                                     {"__builtin__", "getattr"}}) {
    const std::string full = std::string(module) + "." + name;
    // GLOBAL then a call with a harmless-looking argument; refused at the GLOBAL opcode.
    expect_pickle_error(PickleWriter().global(module, name).str("echo pwned").raw("\x85R").done(),
                        {"hostile.pkl", "refusing to load: the pickle asks for global '" + full + "'"});
    // The same through STACK_GLOBAL (protocol 4).
    expect_pickle_error(PickleWriter().raw("\x80\x04").str(module).str(name).raw("\x93").done(),
                        {"refusing to load", "'" + full + "'"});
  }
  // Inside an otherwise valid state dict, as a tensor's rebuild function.
  std::string pkl = state_dict_pickle({{"w", {2}, {1}}});
  const auto at = pkl.find("_rebuild_tensor_v2");
  pkl.replace(at - std::string("torch._utils\n").size(), std::string("torch._utils\n_rebuild_tensor_v2").size(),
              "os\nsystem");
  expect_pickle_error(pkl, {"refusing to load", "'os.system'"});
  expect_pickle_error(PickleWriter().global("torch", "DoubleStorage").done(),
                      {"unsupported storage type 'torch.DoubleStorage'"});
  expect_pickle_error(PickleWriter().global("a\x01\xff", "b").done(), {"refusing to load", "'a\\x01\\xff.b'"});
  expect_pickle_error(PickleWriter().raw("cos").done(), {"GLOBAL operand is unterminated"});
  expect_pickle_error(PickleWriter().raw("c" + std::string(300, 'a') + "\nb\n").done(), {"longer than 256 bytes"});
}

TEST_CASE("bad storages and tensors are named") {
  // Record too small for the tensor.
  expect_load_error(archive(state_dict_pickle({{"w", {2, 3}, {3, 1}}}), {{"0", floats({1, 2, 3, 4, 5})}}),
                    {"hostile.pkl", "tensor 'w' needs 24 bytes", "storage '0' has 20"});
  expect_load_error(archive(state_dict_pickle({{"w", {2}, {1}, 4}}), {{"0", floats({1, 2, 3, 4, 5})}}),
                    {"tensor 'w' needs 24 bytes", "at storage offset 4", "storage '0' has 20"});
  // Declared numel larger than the record.
  expect_load_error(archive(state_dict_pickle({{"w", {2}, {1}, 0, "0", 100}}), {{"0", floats({1, 2})}}),
                    {"storage '0' declares 100 elements of float32", "has only 8 bytes"});
  // Tensor beyond the declared numel (record has room).
  expect_load_error(archive(state_dict_pickle({{"w", {3}, {1}, 0, "0", 2}}), {{"0", floats({1, 2, 3})}}),
                    {"tensor 'w' needs elements up to 3", "storage '0' declares 2"});
  expect_load_error(archive(state_dict_pickle({{"w", {2}, {1}, 0, "7"}}), {{"0", floats({1, 2})}}),
                    {"storage '7' of tensor 'w' has no record 'arc/data/7'"});
  expect_load_error(archive(state_dict_pickle({{"w", {2, 2}, {1, 2}}}), {{"0", floats({1, 2, 3, 4})}}),
                    {"tensor 'w' of shape (2, 2) is not contiguous (stride (1, 2))"});
  expect_load_error(archive(state_dict_pickle({{"w", {2}, {1}}, {"v", {1}, {1}, 0, "0", -1, "HalfStorage"}}),
                            {{"0", floats({1, 2})}}),
                    {"storage '0' is used as float32 and as float16 (tensor 'v')"});
  expect_load_error(
      archive(state_dict_pickle({{"w", {INT64_MAX / 2, 4}, {4, 1}, 0, "0", 1}}), {{"0", floats({1})}}),
      {"tensor 'w'", "overflows int64"});
  expect_load_error(archive(state_dict_pickle({{"w", {INT64_MAX}, {1}, 0, "0", 1}}), {{"0", floats({1})}}),
                    {"tensor 'w'", "overflows 64-bit byte offsets"});
  expect_load_error(archive(state_dict_pickle({{"w", {2}, {1}, INT64_MAX - 1, "0", 1}}), {{"0", floats({1})}}),
                    {"tensor 'w'", "overflows 64-bit byte offsets"});
  expect_pickle_error(state_dict_pickle({{"w", {-2}, {1}, 0, "0", 2}}),
                      {"_rebuild_tensor_v2: size must be a non-negative int"});
  expect_pickle_error(state_dict_pickle({{"w", {2, 2}, {1}}}), {"size (2, 2) and stride (1,) differ in length"});
  expect_pickle_error(
      state_dict_pickle({{"w", std::vector<std::int64_t>(100, 1), std::vector<std::int64_t>(100, 1)}}),
      {"size has 100 dimensions"});
  // Persistent ids and rebuild calls of the wrong form.
  expect_pickle_error(PickleWriter().raw("(").str("module").str("x").raw("tQ").done(),
                      {"unsupported persistent id"});
  expect_pickle_error(PickleWriter().integer(3).raw("Q").done(), {"unsupported persistent id int 3"});
  expect_pickle_error(PickleWriter().global("torch._utils", "_rebuild_tensor_v2").raw("(K\x01tR").done(),
                      {"_rebuild_tensor_v2 called with 1 arguments"});
  expect_pickle_error(
      PickleWriter().global("torch._utils", "_rebuild_tensor_v2").raw("(K\x01K\x01K\x01K\x01K\x01K\x01tR").done(),
      {"the first argument must be a storage"});
  expect_pickle_error(PickleWriter().global("torch._utils", "_rebuild_parameter").raw("(NNNtR").done(),
                      {"the first argument must be a tensor"});
  expect_pickle_error(PickleWriter().global("collections", "OrderedDict").raw("(]tR").done(),
                      {"OrderedDict called with arguments"});
  expect_pickle_error(PickleWriter().global("torch", "FloatStorage").raw(")R").done(),
                      {"torch.FloatStorage may only appear in a persistent id"});
  expect_pickle_error(PickleWriter().raw("K\x01)R").done(), {"REDUCE on a int"});
  // State dict values and keys that are not parameter tensors.
  expect_pickle_error(PickleWriter()
                          .raw("}(X\x01\x00\x00\x00"
                               "aK\x01u"s)
                          .done(),
                      {"no state dict found"});
  std::string mixed = state_dict_pickle({{"w", {2}, {1}}});
  mixed.insert(mixed.size() - 2, "X\x01\x00\x00\x00xK\x05"s);
  expect_error([&] { load_bytes(archive(mixed, {{"0", floats({1, 2})}}), {.key = ""}); }, {"no state dict found"});
  std::string wrapped = PickleWriter().raw("}X\x05\x00\x00\x00model"s).done();
  wrapped.pop_back();
  wrapped += mixed.substr(2, mixed.size() - 3) + "s.";
  expect_load_error(archive(wrapped, {{"0", floats({1, 2})}}), {"state dict entry 'x' is a int 5, not a tensor"});
  expect_pickle_error(PickleWriter().raw("}X\x05\x00\x00\x00model}K\x01N"s).raw("ss").done(),
                      {"the state dict has a key that is a int 1"});
  expect_pickle_error(PickleWriter().raw("}))s").done(), {"a dict key of type tuple is not supported"});
  expect_pickle_error(PickleWriter().raw("]").done(), {"the checkpoint holds a list of 0 items, expected a dict"});
}

TEST_CASE("hostile pickle structure: nesting, memo, lengths, stack, marks, opcodes, truncation") {
  // Deep nesting without a growing stack: a 1-tuple of a 1-tuple of ... (TUPLE1 x 100000).
  expect_pickle_error(PickleWriter().raw("N" + std::string(100000, '\x85')).done(),
                      {"nested deeper than 256 levels"});
  // Deep nesting through lists: push many lists, then APPEND each into the one below.
  expect_pickle_error(PickleWriter().raw(std::string(1000, ']') + std::string(999, 'a')).done(),
                      {"nested deeper than 256"});
  // A list appended into itself, repeatedly, through the memo: refused, no infinite loop.
  {
    std::string self = "]q\x00"s;
    for (int i = 0; i < 300; ++i)
      self +=
          "h\x00"
          "a"s;
    expect_pickle_error(PickleWriter().raw(self).done(), {"nested deeper than 256"});
  }
  // A harmless cycle beside a valid state dict loads.
  {
    std::string pkl = state_dict_pickle({{"w", {2}, {1}}});
    std::string top = PickleWriter().raw("}X\x0a\x00\x00\x00state_dict"s).done();
    top.pop_back();
    // "cycle": a list (memo index 65536, LONG_BINPUT) that contains itself (LONG_BINGET + APPEND).
    top += pkl.substr(2, pkl.size() - 3) +
           "sX\x05\x00\x00\x00"
           "cycle]r\x00\x00\x01\x00j\x00\x00\x01\x00"
           "as."s;
    const auto map = load_bytes(archive(top, {{"0", floats({1, 2})}}));
    CHECK(map.size() == 1);
  }
  // Memo abuse.
  expect_pickle_error(PickleWriter().raw("Nr\xff\xff\xff\xff").done(),
                      {"memo index 4294967295 is beyond the limit"});
  expect_pickle_error(PickleWriter().raw("h\x05").done(), {"memo index 5 was never stored"});
  expect_pickle_error(PickleWriter().raw("j\xff\xff\xff\x7f").done(), {"memo index 2147483647 was never stored"});
  expect_pickle_error(PickleWriter().raw("q\x00"s).done(), {"stack underflow"});
  // Absurd lengths.
  expect_pickle_error(PickleWriter().raw("X\xff\xff\xff\xff").done(),
                      {"a string of 4294967295 bytes runs past the end of the pickle"});
  expect_pickle_error(PickleWriter().raw("\x8d\xff\xff\xff\xff\xff\xff\xff\x7f").done(),
                      {"a string of 9223372036854775807 bytes runs past the end"});
  expect_pickle_error(PickleWriter()
                          .raw("\x8c\x10"
                               "abc")
                          .done(),
                      {"a string of 16 bytes runs past the end"});
  expect_pickle_error(PickleWriter().raw("\x95\xff\xff\xff\xff\xff\xff\xff\xff").done(), {"a frame of"});
  expect_pickle_error(PickleWriter()
                          .raw("\x8a\x09"
                               "123456789")
                          .done(),
                      {"an integer of 9 bytes"});
  // Stack and marks.
  expect_pickle_error(PickleWriter().raw("s").done(), {"stack underflow"});
  expect_pickle_error(PickleWriter().raw("\x86").done(), {"stack underflow"});
  expect_pickle_error(PickleWriter().raw("N(0").done(), {"stack underflow"});  // POP below the mark
  expect_pickle_error(PickleWriter().raw("t").done(), {"no MARK to pop to"});
  expect_pickle_error(PickleWriter().raw(std::string(2000, '(')).done(), {"more than 1024 nested MARKs"});
  expect_pickle_error(PickleWriter().raw("}(K\x01u").done(), {"SETITEMS with an odd number (1)"});
  expect_pickle_error(PickleWriter().raw("](K\x01K\x02u").done(), {"SETITEM(S) on a list"});
  expect_pickle_error(PickleWriter()
                          .raw("}K\x01"
                               "a")
                          .done(),
                      {"APPEND(S) on a dict"});
  expect_pickle_error(PickleWriter().raw("]Nb").done(), {"BUILD on a list"});
  expect_pickle_error(PickleWriter()
                          .raw("}K\x01"
                               "b")
                          .done(),
                      {"BUILD with a int state"});
  // Opcodes outside the supported set, and protocols beyond 5.
  expect_pickle_error(PickleWriter().raw("(cos\nsystem\ni").done(), {"refusing to load"});
  expect_pickle_error(PickleWriter().raw("(i").done(), {"unsupported pickle opcode 0x69 'i'"});
  expect_pickle_error(PickleWriter().raw("\x81").done(), {"unsupported pickle opcode 0x81"});
  expect_pickle_error(PickleWriter().raw("B\x01\x00\x00\x00x"s).done(), {"unsupported pickle opcode 0x42 'B'"});
  expect_pickle_error(PickleWriter().raw("\x80\x06").done(), {"pickle protocol 6 is not supported"});
  expect_pickle_error("", {"pickle byte 0: the pickle ends without a STOP opcode"});
  const std::string valid = state_dict_pickle({{"w", {2}, {1}}});
  for (std::size_t n = 0; n + 1 < valid.size(); ++n)  // every truncation of a valid pickle
    expect_pickle_error(valid.substr(0, n), {"hostile.pkl (arc/data.pkl): pickle byte"});
}

TEST_CASE("pickle limits are enforced (small limits, direct unpickle)") {
  auto run = [](const std::string& s, const pickle::Limits& limits) {
    pickle::unpickle({reinterpret_cast<const std::byte*>(s.data()), s.size()}, "limits", limits);
  };
  pickle::Limits small;
  small.max_stack = 100;
  small.max_objects = 50;
  small.max_memo_index = 10;
  expect_error([&] { run(std::string(101, 'N') + ".", small); }, {"more than 100 values on the pickle stack"});
  expect_error([&] { run(std::string(60, ']') + ".", small); }, {"creates more than 50 objects"});
  expect_error([&] { run("Nq\x0a.", small); }, {"memo index 10 is beyond the limit 10"});
  CHECK_NOTHROW(run(std::string(100, 'N') + ".", small));
  // Object count stays bounded even when every object is popped at once (no stack growth).
  std::string garbage;
  for (int i = 0; i < 60; ++i) garbage += "]0";
  expect_error([&] { run(garbage + "N.", small); }, {"creates more than 50 objects"});
}

TEST_CASE("pickle values: scalars, strings, containers, memo sharing, protocol 4 framing") {
  PickleWriter p;
  p.b = "\x80\x04\x95\x10\x00\x00\x00\x00\x00\x00\x00"s;  // PROTO 4, FRAME
  p.raw("}\x94(");
  p.raw("\x8c\x01i").integer(-7);
  p.raw("\x8c\x01l").raw("\x8a\x08").raw(std::string("\x00\x00\x00\x00\x00\x00\x00\x80", 8));  // INT64_MIN
  p.raw("\x8c\x01m").raw("\x8a\x00"s);                                                         // LONG1 0 = 0
  p.raw("\x8c\x01n").raw("\x8a\x02\xff\x7f");                                                  // 32767
  p.raw(
       "\x8c\x01"
       "f")
      .raw("G\x3f\xf8\x00\x00\x00\x00\x00\x00"s);  // 1.5
  p.raw("\x8c\x01s").str("caf\xc3\xa9");
  p.raw("\x8c\x01t").raw("K\x01\x88N\x87");  // (1, True, None)
  p.raw("\x8c\x01L")
      .raw(
          "](K\x01K\x02"
          "e\x94");
  p.raw("\x8c\x01M").raw("h\x01");      // the same list again, through the memo
  p.raw("\x8c\x01i").raw("M\x34\x12");  // a repeated key replaces the value (Python dict semantics)
  p.raw("u");
  const std::string s = p.done();
  const auto doc = pickle::unpickle({reinterpret_cast<const std::byte*>(s.data()), s.size()}, "values");
  const auto& d = doc.dict(doc.root);
  REQUIRE(d.items.size() == 9);
  CHECK(doc.find(d, "i")->i == 0x1234);
  CHECK(d.items.front().second.i == 0x1234);  // kept its first position
  CHECK(doc.find(d, "l")->i == INT64_MIN);
  CHECK(doc.find(d, "m")->i == 0);
  CHECK(doc.find(d, "n")->i == 32767);
  CHECK(doc.find(d, "f")->f == 1.5);
  CHECK(doc.str(*doc.find(d, "s")) == "caf\xc3\xa9");
  const auto& t = doc.items(*doc.find(d, "t"));
  REQUIRE(t.size() == 3);
  CHECK(t[1].kind == pickle::Kind::Bool);
  CHECK(t[2].kind == pickle::Kind::None);
  CHECK(doc.find(d, "L")->i == doc.find(d, "M")->i);  // one list, two references
  CHECK(doc.items(*doc.find(d, "M")).size() == 2);
  CHECK(doc.find(d, "absent") == nullptr);
}

TEST_CASE("archive-level problems of a checkpoint") {
  const std::string pkl = state_dict_pickle({{"w", {2}, {1}}});
  const std::string two = floats({1, 2});
  CHECK(load_bytes(archive(pkl, {{"0", two}}, "archive/")).size() == 1);  // any folder name
  // No data.pkl, no folder, empty archive.
  {
    zip_test::ZipSpec s;
    s.entries.push_back({"arc/data/0", two});
    expect_load_error(zip_test::layout_zip(s).bytes(), {"not a torch.save checkpoint: no 'arc/data.pkl'"});
    s.entries[0].name = "data.pkl";
    expect_load_error(zip_test::layout_zip(s).bytes(), {"its first entry 'data.pkl' is not inside a folder"});
    expect_load_error(zip_test::layout_zip(zip_test::ZipSpec{}).bytes(), {"empty ZIP archive"});
  }
  // A compressed pickle or storage record.
  for (const char* which : {"arc/data.pkl", "arc/data/0"}) {
    zip_test::ZipSpec s;
    s.entries.push_back({"arc/data.pkl", pkl});
    s.entries.push_back({"arc/data/0", two});
    for (auto& e : s.entries)
      if (e.name == which) e.method = 8;
    expect_load_error(zip_test::layout_zip(s).bytes(), {std::string("entry '") + which + "' is compressed"});
  }
  // A corrupt pickle is caught by its CRC before it is parsed.
  {
    std::string bytes = archive(pkl, {{"0", two}});
    bytes[bytes.find("_rebuild_tensor_v2")] = 'X';
    expect_load_error(bytes, {"entry 'arc/data.pkl' is corrupt: CRC-32"});
  }
  // Byte order record.
  {
    zip_test::ZipSpec s;
    s.entries.push_back({"arc/data.pkl", pkl});
    s.entries.push_back({"arc/byteorder", "big"});
    s.entries.push_back({"arc/data/0", two});
    expect_load_error(zip_test::layout_zip(s).bytes(), {"byte order 'big'", "only little-endian"});
    s.entries[1].data = "little";
    CHECK(load_bytes(zip_test::layout_zip(s).bytes()).size() == 1);
  }
}

TEST_CASE("byte-flip fuzzing of real checkpoints: loads or a named error, never a crash") {
  for (const char* f : {"views.pkl", "fp16_dcae.pkl", "zip64_full.pkl"}) {
    std::ifstream in(kPklDir + f, std::ios::binary);
    const std::string bytes{std::istreambuf_iterator<char>(in), {}};
    std::size_t loaded = 0, refused = 0;
    for (std::size_t i = 0; i < bytes.size(); ++i)
      for (unsigned char x : {0x01, 0x20, 0xff}) {
        std::string b = bytes;
        b[i] = char(static_cast<unsigned char>(b[i]) ^ x);
        try {
          const auto map = load_bytes(b, {.key = "", .verify_checksums = true});
          for (const auto& [name, t] : map.entries())  // every view lies inside the buffer
            if (!t.bytes.empty())
              CHECK((t.bytes.data() >= reinterpret_cast<const std::byte*>(b.data()) &&
                     t.bytes.data() + t.bytes.size() <= reinterpret_cast<const std::byte*>(b.data()) + b.size()));
          ++loaded;
        } catch (const Error&) {
          ++refused;
        }
      }
    CHECK(loaded + refused == 3 * bytes.size());
    MESSAGE(std::string(f), ": ", refused, " corruptions refused, ", loaded,
            " harmless (timestamps, padding, unused fields)");
  }
}

TEST_CASE("a sparse multi-GB checkpoint (ZIP64, storage > 4 GiB) loads zero-copy in milliseconds") {
  const std::int64_t n = (std::int64_t{1} << 30) + 5;  // 4 GiB + 20 bytes of float32
  const std::string pkl =
      state_dict_pickle({{"huge", {n}, {1}}, {"tail", {5}, {1}, n - 5}, {"small", {2}, {1}, 0, "1"}});
  zip_test::ZipSpec s;
  s.zip64 = true;
  s.entries.push_back({"big/data.pkl", pkl});
  zip_test::ZipSpec::Entry huge{"big/data/0", floats({1.5f, 2.5f}), static_cast<std::uint64_t>(n) * 4};
  huge.descriptor = true;
  s.entries.push_back(huge);
  s.entries.push_back({"big/data/1", floats({7, 8})});  // its local header lies beyond 4 GiB
  s.entries.push_back({"big/version", "3\n"});
  const auto layout = zip_test::layout_zip(s);
  const auto path = (std::filesystem::temp_directory_path() / "epona_test_sparse_checkpoint.pkl").string();
  try {
    layout.write_sparse(path);
  } catch (const Error& e) {
    MESSAGE("skipped: cannot write a sparse file: ", e.what());
    return;
  }
  {
    const auto t0 = std::chrono::steady_clock::now();
    const auto map = load_weights(path);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    MESSAGE("loaded a ", layout.size / 1e9, " GB checkpoint in ", ms, " ms");
    CHECK(ms < 1000);
    const auto& h = map.at("huge");
    CHECK(h.shape == Shape{n});
    CHECK(h.bytes.size() == static_cast<std::size_t>(n) * 4);
    CHECK(load_as_float(h.bytes.data(), h.dtype, 1) == 2.5f);
    CHECK(map.at("tail").bytes.data() == h.bytes.data() + (n - 5) * 4);
    CHECK(to_tensor<float>(map.at("small")).at(1) == 8.f);
  }
  std::filesystem::remove(path);
}

TEST_CASE("byte-flip fuzzing of the unpickler (CRC kept valid): loads or a named error, never a crash") {
  for (const std::string stem : {"views", "fp16_dcae", "bf16_world"}) {
    const auto zip = ZipArchive::open(kPklDir + stem + ".pkl");
    auto text = [&](const ZipEntry& e) {
      const auto b = zip.data(e);
      return std::string(reinterpret_cast<const char*>(b.data()), b.size());
    };
    const std::string pkl = text(zip.at(stem + "/data.pkl"));
    std::map<std::string, std::string> storages;
    const std::string data_dir = stem + "/data/";
    for (const auto& e : zip.entries())
      if (e.name.rfind(data_dir, 0) == 0) storages[e.name.substr(data_dir.size())] = text(e);
    REQUIRE(load_bytes(archive(pkl, storages)).size() > 0);
    std::size_t loaded = 0, refused = 0;
    for (std::size_t i = 0; i < pkl.size(); ++i)
      for (unsigned char x : {0x01, 0x10, 0x80, 0xff}) {
        std::string p = pkl;
        p[i] = char(static_cast<unsigned char>(p[i]) ^ x);
        try {
          load_bytes(archive(p, storages));
          ++loaded;
        } catch (const Error& e) {
          ++refused;
          CHECK(std::string(e.what()).find("hostile.pkl") == 0);
        }
      }
    CHECK(loaded + refused == 4 * pkl.size());
    CHECK(refused > loaded);
    MESSAGE(stem, ": ", refused, " pickle corruptions refused, ", loaded,
            " loaded (e.g. changed values or names)");
  }
}
