// epona/io/npy.hpp — NumPy .npy files (format versions 1.0, 2.0, 3.0): a strict reader
// (no eval: a small parser for the header dict, little-endian float16/32/64, C order,
// sizes checked against the file) and an atomic writer (temp name + rename). Mirrors what
// numpy.load/numpy.save do for the official demo's pose.npy/yaw.npy and for our outputs.
#pragma once

#include <bit>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <span>
#include <string>
#include <string_view>
#include <system_error>
#include <type_traits>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"

namespace epona::io {

static_assert(std::endian::native == std::endian::little,
              "epona's file readers assume a little-endian host");

// ---- whole-file helpers shared by the small-file readers/writers ------------------------

// Reads a regular file into memory; errors name the path.
inline std::vector<std::byte> read_whole_file(const std::filesystem::path& path) {
  std::error_code ec;
  EPONA_CHECK(std::filesystem::is_regular_file(path, ec), path.string(),
              ": not found or not a regular file");
  const auto size = std::filesystem::file_size(path, ec);
  EPONA_CHECK(!ec, path.string(), ": cannot get the file size (", ec.message(), ")");
  std::vector<std::byte> bytes(static_cast<std::size_t>(size));
  std::ifstream in(path, std::ios::binary);
  EPONA_CHECK(in.good(), path.string(), ": cannot open for reading");
  in.read(reinterpret_cast<char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  EPONA_CHECK(in.gcount() == static_cast<std::streamsize>(bytes.size()), path.string(),
              ": read ", in.gcount(), " of ", bytes.size(), " bytes");
  return bytes;
}


// ---- the format ---------------------------------------------------------------------

enum class NpyDType : std::uint8_t { F16, F32, F64 };

inline std::size_t npy_itemsize(NpyDType t) {
  return t == NpyDType::F16 ? 2 : t == NpyDType::F32 ? 4 : 8;
}
inline std::string_view npy_descr(NpyDType t) {
  return t == NpyDType::F16 ? "<f2" : t == NpyDType::F32 ? "<f4" : "<f8";
}

struct NpyHeader {
  NpyDType dtype = NpyDType::F32;
  Shape shape;
  std::size_t data_offset = 0;  // bytes from the start of the file to the first element
};

template <class T>
struct NpyArray {
  Tensor<T> values;  // converted to T, C order, shape as in the file
  NpyDType dtype;    // what the file held
};

namespace npy_detail {

inline constexpr std::size_t kMaxHeaderBytes = 1 << 20;  // numpy itself refuses > 10000 by default
inline constexpr std::size_t kMaxRank = 64;               // numpy 2's NPY_MAXDIMS

// A recursive-descent parser for the one Python literal numpy writes as the header:
// {'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), } — strings, True/False,
// tuples of non-negative ints; anything else is an error (no eval).
class HeaderParser {
 public:
  HeaderParser(std::string_view text, const std::string& source) : s_(text), src_(source) {}

  NpyHeader parse() {
    bool have_descr = false, have_order = false, have_shape = false;
    NpyHeader h;
    skip_space();
    expect('{');
    skip_space();
    while (peek() != '}') {
      const std::string key = parse_string("a dict key");
      skip_space();
      expect(':');
      skip_space();
      if (key == "descr") {
        EPONA_CHECK(!have_descr, bad("duplicate key 'descr'"));
        have_descr = true;
        h.dtype = dtype_from_descr(parse_value_string("'descr'"));
      } else if (key == "fortran_order") {
        EPONA_CHECK(!have_order, bad("duplicate key 'fortran_order'"));
        have_order = true;
        EPONA_CHECK(!parse_bool(), src_, ": Fortran-order (column-major) arrays are not supported; "
                                         "save a C-contiguous array (numpy.ascontiguousarray)");
      } else if (key == "shape") {
        EPONA_CHECK(!have_shape, bad("duplicate key 'shape'"));
        have_shape = true;
        h.shape = parse_shape();
      } else {
        fail(bad("unexpected key '" + key + "' (expected descr, fortran_order, shape)"));
      }
      skip_space();
      if (peek() == ',') {
        ++pos_;
        skip_space();
      } else {
        EPONA_CHECK(peek() == '}', bad("expected ',' or '}'"));
      }
    }
    ++pos_;
    while (pos_ < s_.size()) {
      EPONA_CHECK(is_space(s_[pos_]), bad("unexpected text after the closing '}'"));
      ++pos_;
    }
    EPONA_CHECK(have_descr && have_order && have_shape,
                bad("missing key(s): needs 'descr', 'fortran_order' and 'shape'"));
    return h;
  }

 private:
  static bool is_space(char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r'; }
  char peek() const {
    EPONA_CHECK(pos_ < s_.size(), bad("header ends early"));
    return s_[pos_];
  }
  void skip_space() {
    while (pos_ < s_.size() && is_space(s_[pos_])) ++pos_;
  }
  void expect(char c) {
    EPONA_CHECK(peek() == c, bad(std::string("expected '") + c + "'"));
    ++pos_;
  }
  std::string bad(const std::string& what) const {
    return detail::concat(src_, ": malformed .npy header at character ", pos_, ": ", what,
                          " (header: ", std::string(s_.substr(0, 200)), ")");
  }

  std::string parse_string(const char* what) {
    const char quote = peek();
    EPONA_CHECK(quote == '\'' || quote == '"', bad(std::string("expected ") + what + " in quotes"));
    const auto end = s_.find(quote, pos_ + 1);
    EPONA_CHECK(end != std::string_view::npos, bad("unterminated string"));
    std::string out(s_.substr(pos_ + 1, end - pos_ - 1));
    EPONA_CHECK(out.find('\\') == std::string::npos, bad("escape sequences are not supported"));
    pos_ = end + 1;
    return out;
  }
  std::string parse_value_string(const char* key) {
    EPONA_CHECK(peek() == '\'' || peek() == '"',
                bad(std::string(key) + " must be a string (structured dtypes are not supported)"));
    return parse_string(key);
  }
  bool parse_bool() {
    if (s_.substr(pos_, 4) == "True") return pos_ += 4, true;
    if (s_.substr(pos_, 5) == "False") return pos_ += 5, false;
    fail(bad("'fortran_order' must be True or False"));
  }
  std::int64_t parse_int() {
    EPONA_CHECK(peek() >= '0' && peek() <= '9', bad("expected a non-negative integer in 'shape'"));
    std::int64_t v = 0;
    while (pos_ < s_.size() && s_[pos_] >= '0' && s_[pos_] <= '9') {
      EPONA_CHECK(v <= (INT64_MAX - 9) / 10, bad("dimension too large in 'shape'"));
      v = v * 10 + (s_[pos_++] - '0');
    }
    if (pos_ < s_.size() && s_[pos_] == 'L') ++pos_;  // Python 2 long suffix
    return v;
  }
  // (), (n,), (n, m), (n, m,) — a 1-tuple needs its comma, as in Python.
  Shape parse_shape() {
    EPONA_CHECK(peek() == '(', bad("'shape' must be a tuple"));
    ++pos_;
    Shape shape;
    bool trailing_comma = false;
    skip_space();
    while (peek() != ')') {
      EPONA_CHECK(shape.size() < kMaxRank, bad("'shape' has more than 64 dimensions"));
      shape.push_back(parse_int());
      skip_space();
      trailing_comma = peek() == ',';
      if (trailing_comma) {
        ++pos_;
        skip_space();
      } else {
        EPONA_CHECK(peek() == ')', bad("expected ',' or ')' in 'shape'"));
      }
    }
    ++pos_;
    EPONA_CHECK(shape.size() != 1 || trailing_comma, bad("'shape' (n) is an int, not a tuple; write (n,)"));
    return shape;
  }
  NpyDType dtype_from_descr(const std::string& d) {
    if (d == "<f4") return NpyDType::F32;
    if (d == "<f8") return NpyDType::F64;
    if (d == "<f2") return NpyDType::F16;
    if (!d.empty() && d[0] == '>')
      fail(src_, ": big-endian dtype '", d, "' is not supported; save with dtype '<", d.substr(1), "'");
    fail(src_, ": unsupported dtype '", d, "'; epona reads float16/32/64 ('<f2', '<f4', '<f8')");
  }

  std::string_view s_;
  const std::string& src_;
  std::size_t pos_ = 0;
};

inline std::uint32_t read_le(const std::byte* p, std::size_t n) {
  std::uint32_t v = 0;
  for (std::size_t i = 0; i < n; ++i) v |= static_cast<std::uint32_t>(p[i]) << (8 * i);
  return v;
}

template <class T>
T element(const std::byte* data, NpyDType t, std::size_t i) {
  switch (t) {
    case NpyDType::F16: return static_cast<T>(load_as_float(data, DType::F16, i));
    case NpyDType::F32: return static_cast<T>(load_as_float(data, DType::F32, i));
    case NpyDType::F64: { double d; std::memcpy(&d, data + 8 * i, 8); return static_cast<T>(d); }
  }
  fail("npy: unknown dtype");
}

}  // namespace npy_detail

// Parses and validates the preamble and header of an in-memory .npy file; `source` names
// it in errors. Checks that the data after the header is exactly shape x itemsize bytes.
inline NpyHeader parse_npy_header(std::span<const std::byte> file, const std::string& source) {
  static constexpr unsigned char magic[6] = {0x93, 'N', 'U', 'M', 'P', 'Y'};
  EPONA_CHECK(file.size() >= 10, source, ": not a .npy file (", file.size(), " bytes, too short)");
  EPONA_CHECK(std::memcmp(file.data(), magic, 6) == 0, source, ": not a .npy file (bad magic)");
  const auto major = static_cast<unsigned>(file[6]), minor = static_cast<unsigned>(file[7]);
  EPONA_CHECK((major == 1 || major == 2 || major == 3) && minor == 0, source,
              ": unsupported .npy format version ", major, ".", minor, " (reads 1.0, 2.0, 3.0)");
  const std::size_t len_bytes = major == 1 ? 2 : 4;
  EPONA_CHECK(file.size() >= 8 + len_bytes, source, ": truncated .npy preamble");
  const std::size_t header_len = npy_detail::read_le(file.data() + 8, len_bytes);
  const std::size_t header_start = 8 + len_bytes;
  EPONA_CHECK(header_len <= npy_detail::kMaxHeaderBytes, source, ": .npy header length ", header_len,
              " is implausibly large");
  EPONA_CHECK(header_start + header_len <= file.size(), source, ": .npy header length ", header_len,
              " runs past the end of the file (", file.size(), " bytes)");
  const std::string_view text(reinterpret_cast<const char*>(file.data() + header_start), header_len);
  for (char c : text)
    EPONA_CHECK(static_cast<unsigned char>(c) < 0x80 && c != '\0', source,
                ": .npy header contains a non-ASCII or NUL byte");

  NpyHeader h = npy_detail::HeaderParser(text, source).parse();
  h.data_offset = header_start + header_len;
  const std::size_t item = npy_itemsize(h.dtype);
  std::size_t need = item;  // bytes of data the shape asks for, overflow-checked
  for (const auto d : h.shape) {
    EPONA_CHECK(d == 0 || need <= SIZE_MAX / static_cast<std::size_t>(d), source, ": shape ",
                shape_str(h.shape), " of dtype '", npy_descr(h.dtype), "' is too large");
    need *= static_cast<std::size_t>(d);
  }
  const std::size_t have = file.size() - h.data_offset;
  EPONA_CHECK(need == have, source, ": shape ", shape_str(h.shape), " of dtype '", npy_descr(h.dtype),
              "' needs ", need, " data bytes, the file has ", have, " after the header");
  return h;
}

// Parses an in-memory .npy file into a Tensor<T> (T = float or double; values converted).
template <class T = float>
NpyArray<T> parse_npy(std::span<const std::byte> file, const std::string& source) {
  static_assert(std::is_same_v<T, float> || std::is_same_v<T, double>);
  const NpyHeader h = parse_npy_header(file, source);
  Tensor<T> values(h.shape);
  const std::byte* data = file.data() + h.data_offset;
  const auto n = static_cast<std::size_t>(values.numel());
  const bool same_type = h.dtype == (std::is_same_v<T, float> ? NpyDType::F32 : NpyDType::F64);
  if (same_type) {
    if (n) std::memcpy(values.data(), data, n * sizeof(T));
  } else {
    for (std::size_t i = 0; i < n; ++i) values.data()[i] = npy_detail::element<T>(data, h.dtype, i);
  }
  return {std::move(values), h.dtype};
}

template <class T = float>
NpyArray<T> read_npy(const std::filesystem::path& path) {
  const auto bytes = read_whole_file(path);
  return parse_npy<T>(bytes, path.string());
}

// The preamble and header dict of a .npy file, format 1.0 (a header of at most 64 dimensions
// always fits its 16-bit length), padded so the data starts at a multiple of 64 bytes.
inline std::string npy_preamble(std::string_view descr, const std::vector<std::int64_t>& shape) {
  std::string dims = "(";
  for (std::size_t i = 0; i < shape.size(); ++i) dims += (i ? ", " : "") + std::to_string(shape[i]);
  dims += shape.size() == 1 ? ",)" : ")";
  std::string header = "{'descr': '" + std::string(descr) + "', 'fortran_order': False, 'shape': " + dims + ", }";
  const std::size_t preamble = 10;  // magic, version 1.0, uint16 header length
  header.resize((preamble + header.size() + 1 + 63) / 64 * 64 - preamble - 1, ' ');
  header.push_back('\n');
  EPONA_CHECK(shape.size() <= npy_detail::kMaxRank && header.size() <= 65535,
              "write_npy: shape ", dims, " has too many dimensions");
  std::string out = "\x93NUMPY";
  out += '\x01';
  out += '\x00';
  out += static_cast<char>(header.size() & 0xff);
  out += static_cast<char>(header.size() >> 8);
  return out + header;
}

// Serialises a tensor as a .npy file ('<f4' for float, '<f8' for double).
template <class T>
std::string to_npy_bytes(const Tensor<T>& t) {
  static_assert(std::is_same_v<T, float> || std::is_same_v<T, double>);
  std::vector<std::int64_t> shape(t.shape().begin(), t.shape().end());
  std::string out = npy_preamble(std::is_same_v<T, float> ? "<f4" : "<f8", shape);
  out.append(reinterpret_cast<const char*>(t.data()), t.nbytes());
  return out;
}

template <class T>
void write_npy(const std::filesystem::path& path, const Tensor<T>& t) {
  write_atomically(path, to_npy_bytes(t));
}

// Writes raw C-order data of dtype `descr` ('|u1' for uint8 images, '<f8', ...) and `shape`;
// `bytes` must hold exactly the product of the shape times the item size.
inline void write_npy(const std::filesystem::path& path, std::string_view descr, const std::vector<std::int64_t>& shape,
                      std::span<const std::byte> bytes) {
  const std::string head = npy_preamble(descr, shape);
  write_atomically(path, [&](AtomicFileSink& out) {
    out.write(head);
    out.write(bytes.data(), bytes.size());
  });
}

}  // namespace epona::io
