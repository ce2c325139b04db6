// epona/io/safetensors.hpp — reads and writes the safetensors format (8-byte little-endian
// header length, JSON header name -> {dtype, shape, data_offsets}, optional "__metadata__",
// raw little-endian data). Reading memory-maps the file; every offset and size is checked
// against the file and the shape, so hostile files give an epona::Error naming file and problem.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <functional>
#include <map>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/core/printable.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/io/json_reader.hpp"
#include "epona/io/mmap.hpp"
#include "epona/io/tensor_map.hpp"

namespace epona::io {

using SafetensorsMetadata = std::map<std::string, std::string>;

struct SafetensorsFile {
  TensorMap tensors;
  SafetensorsMetadata metadata;  // the header's "__metadata__" (string -> string), may be empty
};

namespace safetensors_detail {
using nlohmann::json;

// The format's own limit (the reference implementation refuses larger headers).
inline constexpr std::uint64_t max_header_bytes = 100'000'000;
inline constexpr int max_header_depth = 3;  // top object > entry > shape list; deeper is hostile

inline std::string_view dtype_code(DType t) {
  switch (t) {
    case DType::F32: return "F32";
    case DType::BF16: return "BF16";
    case DType::F16: return "F16";
    case DType::I64: return "I64";
  }
  return "?";
}

inline DType dtype_from_code(const std::string& code, const std::string& where) {
  for (DType t : {DType::F32, DType::BF16, DType::F16, DType::I64})
    if (code == dtype_code(t)) return t;
  fail(where, " has dtype '", code, "', which is not supported (F32, BF16, F16, I64)");
}

inline std::uint64_t read_u64_le(const std::byte* p) {
  std::uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | static_cast<std::uint8_t>(p[i]);
  return v;
}

// What a file that is no weight file looks like, from its first bytes: "text, starting
// \"...\"" or "binary, starting with bytes 89 50 4e 47 ...", for an error a user can act on.
inline std::string describe_start(std::span<const std::byte> bytes) {
  const std::size_t n = std::min<std::size_t>(bytes.size(), 24);
  std::string text;
  bool is_text = true;
  for (std::size_t i = 0; i < n; ++i) {
    const auto c = static_cast<unsigned char>(bytes[i]);
    is_text = is_text && (c >= 0x20 ? c < 0x7f || c >= 0x80 : c == '\n' || c == '\r' || c == '\t');
    text += static_cast<char>(c);
  }
  if (is_text) return "text, starting \"" + printable(text, 24) + "\"";
  std::string hex = "binary, starting with bytes";
  for (std::size_t i = 0; i < std::min<std::size_t>(n, 8); ++i) {
    char b[4];
    std::snprintf(b, sizeof b, " %02x", static_cast<unsigned>(bytes[i]));
    hex += b;
  }
  return hex;
}

// Parses the header; duplicate tensor names are an error (a JSON object would keep only one).
// Not nlohmann's callback parser: after every closed object it rescans the enclosing object for
// discarded values, which made a header of 80k tensors take 237 s (quadratic); the bounded
// builder does constant work per value (`work` counts it for the linearity test).
inline json parse_header(std::string_view text, const std::string& source, JsonWork* work = nullptr) {
  JsonLimits lim;
  lim.max_depth = max_header_depth;
  json header = parse_json(text, source + ": header", lim, work);
  EPONA_CHECK(header.is_object(), source, ": header is not a JSON object but ", header.type_name());
  return header;
}

inline SafetensorsMetadata read_metadata(const json& m, const std::string& source) {
  EPONA_CHECK(m.is_object(), source, ": __metadata__ must be an object of strings, got ", m.type_name());
  SafetensorsMetadata out;
  for (auto it = m.begin(); it != m.end(); ++it) {
    EPONA_CHECK(it->is_string(), source, ": __metadata__ value '", printable(it.key()), "' must be a string, got ",
                it->type_name());
    out.emplace(it.key(), it->get<std::string>());
  }
  return out;
}

inline std::uint64_t non_negative_integer(const json& v, const std::string& what) {
  EPONA_CHECK(v.is_number_unsigned() || (v.is_number_integer() && v.get<std::int64_t>() >= 0), what,
              " must be a non-negative integer, got ", json_brief(v));
  return v.get<std::uint64_t>();
}

struct Entry {
  std::string name;
  DType dtype;
  Shape shape;
  std::uint64_t begin, end;  // byte range within the data section
};

// One header entry, checked on its own: types, shape, and that the byte range fits the data
// section and equals numel * dtype size.
inline Entry read_entry(const std::string& name, const json& v, std::uint64_t data_bytes,
                        const std::string& source) {
  const std::string where = source + ": tensor '" + printable(name) + "'";
  EPONA_CHECK(v.is_object(), where, " header entry must be an object, got ", v.type_name());
  for (const char* key : {"dtype", "shape", "data_offsets"})
    EPONA_CHECK(v.contains(key), where, " has no '", key, "'");
  EPONA_CHECK(v["dtype"].is_string(), where, " dtype must be a string, got ", json_brief(v["dtype"]));
  Entry e{name, dtype_from_code(v["dtype"].get<std::string>(), where), {}, 0, 0};

  const json& shape = v["shape"];
  EPONA_CHECK(shape.is_array(), where, " shape must be a list, got ", json_brief(shape));
  for (const auto& d : shape) {
    const auto extent = non_negative_integer(d, where + " shape entry");
    EPONA_CHECK(extent <= std::uint64_t(INT64_MAX), where, " shape entry ", extent, " is absurd");
    e.shape.push_back(static_cast<std::int64_t>(extent));
  }
  std::int64_t numel = 0;
  try {
    numel = shape_numel(e.shape);
  } catch (const Error& err) {
    fail(where, ": ", err.what());
  }
  const json& off = v["data_offsets"];
  EPONA_CHECK(off.is_array() && off.size() == 2, where, " data_offsets must be [begin, end], got ", json_brief(off));
  e.begin = non_negative_integer(off[0], where + " data_offsets begin");
  e.end = non_negative_integer(off[1], where + " data_offsets end");
  EPONA_CHECK(e.begin <= e.end, where, " data_offsets [", e.begin, ", ", e.end, ") end before they begin");
  EPONA_CHECK(e.end <= data_bytes, where, " data_offsets [", e.begin, ", ", e.end,
              ") run past the end of the data section (", data_bytes, " bytes; file truncated?)");
  // numel * size == span, compared without forming a product that could overflow.
  const std::uint64_t elem = dtype_size(e.dtype), span = e.end - e.begin;
  EPONA_CHECK(std::uint64_t(numel) <= span / elem && std::uint64_t(numel) * elem == span, where, " of shape ",
              shape_str(e.shape), " and dtype ", dtype_code(e.dtype), " needs ", numel, " elements of ", elem,
              " bytes, its data_offsets span ", span, " bytes");
  return e;
}

// Non-empty byte ranges must not share a byte.
inline void check_no_overlap(std::vector<Entry>& entries, const std::string& source) {
  std::sort(entries.begin(), entries.end(), [](const Entry& a, const Entry& b) {
    return a.begin != b.begin ? a.begin < b.begin : a.end < b.end;
  });
  const Entry* prev = nullptr;
  for (const auto& e : entries) {
    if (e.begin == e.end) continue;
    if (prev)
      EPONA_CHECK(e.begin >= prev->end, source, ": tensors '", printable(prev->name), "' [", prev->begin, ", ",
                  prev->end, ") and '", printable(e.name), "' [", e.begin, ", ", e.end, ") overlap");
    prev = &e;
  }
}
}  // namespace safetensors_detail

// Parses a safetensors image held in memory; the tensors view `bytes`, which `keepalive` owns.
inline SafetensorsFile parse_safetensors(std::span<const std::byte> bytes, const std::string& source,
                                         std::shared_ptr<const void> keepalive) {
  namespace sd = safetensors_detail;
  EPONA_CHECK(!bytes.empty(), source, ": empty file (0 bytes)");
  EPONA_CHECK(bytes.size() >= 8, source, ": truncated: ", bytes.size(),
              " bytes, shorter than the 8-byte header length");
  const std::uint64_t header_len = sd::read_u64_le(bytes.data());
  // A safetensors header is JSON, so byte 8 is '{': without it the file is no weight file at all
  // (a text file's first 8 bytes read as a header length of 10^18), and saying so is the help.
  EPONA_CHECK(header_len <= bytes.size() - 8 || bytes.size() <= 8 || bytes[8] == std::byte{'{'}, source,
              ": not a checkpoint: neither safetensors (8-byte length, JSON header) nor a PyTorch .pkl (ZIP or "
              "pickle); the file is ", sd::describe_start(bytes));
  EPONA_CHECK(header_len <= bytes.size() - 8, source, ": header length ", header_len,
              " runs past the end of the file (", bytes.size(), " bytes; truncated or not safetensors)");
  EPONA_CHECK(header_len <= sd::max_header_bytes, source, ": header length ", header_len,
              " exceeds the format's limit of ", sd::max_header_bytes, " bytes");
  const auto* text = reinterpret_cast<const char*>(bytes.data() + 8);
  const auto header = sd::parse_header(std::string_view(text, header_len), source);

  const std::uint64_t data_offset = 8 + header_len;
  const std::uint64_t data_bytes = bytes.size() - data_offset;
  SafetensorsFile out{TensorMap(source), {}};
  std::vector<sd::Entry> entries;
  for (auto it = header.begin(); it != header.end(); ++it) {
    if (it.key() == "__metadata__") {
      out.metadata = sd::read_metadata(*it, source);
      continue;
    }
    entries.push_back(sd::read_entry(it.key(), *it, data_bytes, source));
  }
  sd::check_no_overlap(entries, source);
  for (const auto& e : entries) {
    const auto span = bytes.subspan(data_offset + e.begin, e.end - e.begin);
    out.tensors.add(e.name, RawTensor{e.dtype, e.shape, span});
  }
  out.tensors.keep_alive(std::const_pointer_cast<void>(std::move(keepalive)));
  return out;
}

// Memory-maps and parses `path`. Tensor bytes stay valid while any copy of the map lives.
// Data is not necessarily aligned to its element size: read it with to_tensor / memcpy.
inline SafetensorsFile read_safetensors(const std::string& path) {
  auto file = MappedFile::open(path);
  const auto bytes = file->bytes();
  return parse_safetensors(bytes, path, std::move(file));
}

inline TensorMap load_safetensors(const std::string& path) { return read_safetensors(path).tensors; }

// A RawTensor viewing a host tensor's memory (the tensor must outlive the view).
template <class T>
RawTensor raw_view(const Tensor<T, Cpu>& t) {
  return RawTensor{dtype_of<T>::value, t.shape(),
                   std::span<const std::byte>(reinterpret_cast<const std::byte*>(t.data()), t.nbytes())};
}

// How save_safetensors stores tensors in another dtype (epona convert --dtype): `dtype` gives the
// dtype a tensor is stored as, `write` writes its bytes in that dtype (streamed, so a conversion
// needs no second copy of the weights in memory). Empty: every tensor as it is.
struct SafetensorsEncoding {
  std::function<DType(const std::string& name, const RawTensor& t)> dtype;
  std::function<void(const std::string& name, const RawTensor& t, DType to, AtomicFileSink& out)> write;
};

// Writes `tensors` (in name order, packed) and `metadata`; the header is padded with spaces
// to a multiple of 8 so that data starts aligned. Written atomically (io/atomic_file.hpp), so
// a failure or a crash (also one thrown by `encoding.write`) never leaves a half-written file
// under `path`.
inline void save_safetensors(const std::string& path, const TensorMap& tensors,
                             const SafetensorsMetadata& metadata = {}, const SafetensorsEncoding& encoding = {}) {
  namespace sd = safetensors_detail;
  const auto stored = [&](const std::string& name, const RawTensor& t) {
    return encoding.dtype ? encoding.dtype(name, t) : t.dtype;
  };
  nlohmann::json header = nlohmann::json::object();
  if (!metadata.empty()) header["__metadata__"] = metadata;
  std::uint64_t offset = 0;
  for (const auto& [name, t] : tensors.entries()) {
    EPONA_CHECK(name != "__metadata__", path, ": a tensor may not be named __metadata__");
    const DType d = stored(name, t);
    const std::uint64_t bytes = static_cast<std::uint64_t>(t.numel()) * dtype_size(d);
    header[name] = {{"dtype", sd::dtype_code(d)}, {"shape", t.shape}, {"data_offsets", {offset, offset + bytes}}};
    offset += bytes;
  }
  std::string text = header.dump();
  text.resize((text.size() + 7) / 8 * 8, ' ');

  write_atomically(path, [&](AtomicFileSink& out) {
    unsigned char len[8];
    for (int i = 0; i < 8; ++i) len[i] = static_cast<unsigned char>((std::uint64_t(text.size()) >> (8 * i)) & 0xff);
    out.write(len, 8);
    out.write(text);
    for (const auto& [name, t] : tensors.entries()) {
      const DType d = stored(name, t);
      if (d == t.dtype) {
        out.write(t.bytes.data(), t.bytes.size());
        continue;
      }
      const std::uint64_t before = out.bytes_written();
      encoding.write(name, t, d, out);
      EPONA_CHECK(out.bytes_written() - before == static_cast<std::uint64_t>(t.numel()) * dtype_size(d), path,
                  ": the encoding wrote ", out.bytes_written() - before, " bytes for '", printable(name, 200),
                  "' as ", dtype_name(d), ", its header says ", static_cast<std::uint64_t>(t.numel()) * dtype_size(d));
    }
  });
}

}  // namespace epona::io
