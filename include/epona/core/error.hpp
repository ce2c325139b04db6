// epona/core/error.hpp — the one exception type of the library and the check macros.
// Every failure on bad input throws epona::Error with a message that names the
// problem (file, tensor name, expected vs. actual); nothing calls abort().
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>

namespace epona {

class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

namespace detail {
template <class... Args>
std::string concat(Args&&... args) {
  std::ostringstream os;
  (os << ... << std::forward<Args>(args));
  return os.str();
}
}  // namespace detail

// Throws epona::Error whose message is the concatenation of the arguments.
template <class... Args>
[[noreturn]] void fail(Args&&... args) {
  throw Error(detail::concat(std::forward<Args>(args)...));
}

}  // namespace epona

// EPONA_CHECK(cond, "message parts", ...): throws epona::Error when cond is false.
#define EPONA_CHECK(cond, ...)                                  \
  do {                                                          \
    if (!(cond)) ::epona::fail(__VA_ARGS__);                    \
  } while (0)
