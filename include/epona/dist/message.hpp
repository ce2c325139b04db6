// epona/dist/message.hpp — the bytes of a result sent between ranks: values appended in order by a
// MessageWriter and read back in the same order by a MessageReader, which checks every read
// against the end (a short or corrupt message is an epona::Error, never a read past it). Both
// ends are the same program, so numbers travel as their bytes, exactly (no text round trip).
#pragma once

#include <cstdint>
#include <cstring>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/core/error.hpp"

namespace epona::dist {

class MessageWriter {
 public:
  template <class T>
    requires std::is_arithmetic_v<T>
  MessageWriter& put(T v) {
    bytes_.append(reinterpret_cast<const char*>(&v), sizeof v);
    return *this;
  }
  MessageWriter& put(const std::string& s) {
    put(static_cast<std::uint64_t>(s.size()));
    bytes_ += s;
    return *this;
  }
  template <class T>
  MessageWriter& put(const std::vector<T>& v) {
    put(static_cast<std::uint64_t>(v.size()));
    for (const T& x : v) put(x);
    return *this;
  }
  const std::string& bytes() const { return bytes_; }

 private:
  std::string bytes_;
};

class MessageReader {
 public:
  explicit MessageReader(const std::string& bytes) : bytes_(bytes) {}
  template <class T>
    requires std::is_arithmetic_v<T>
  T get() {
    T v;
    std::memcpy(&v, take(sizeof v), sizeof v);
    return v;
  }
  std::string get_string() {
    const std::uint64_t n = get<std::uint64_t>();
    EPONA_CHECK(n <= remaining(), "a message from another rank is cut short (a text of ", n, " bytes, ", remaining(),
                " left)");
    return std::string(take(static_cast<std::size_t>(n)), static_cast<std::size_t>(n));
  }
  template <class T>
  std::vector<T> get_vector() {
    const std::uint64_t n = get<std::uint64_t>();
    EPONA_CHECK(n <= remaining() / sizeof(T), "a message from another rank is cut short (", n, " values, ",
                remaining(), " bytes left)");
    std::vector<T> v;
    for (std::uint64_t i = 0; i < n; ++i) v.push_back(get<T>());
    return v;
  }
  std::size_t remaining() const { return bytes_.size() - at_; }
  bool done() const { return at_ == bytes_.size(); }

 private:
  const char* take(std::size_t n) {
    EPONA_CHECK(n <= remaining(), "a message from another rank is cut short (", n, " bytes wanted, ", remaining(),
                " left)");
    const char* p = bytes_.data() + at_;
    at_ += n;
    return p;
  }
  const std::string& bytes_;
  std::size_t at_ = 0;
};

}  // namespace epona::dist
