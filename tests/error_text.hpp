// The message of the epona::Error a call throws ("" when it throws none), for tests that check
// what an error names.
#pragma once

#include <functional>
#include <string>

#include "epona/core/error.hpp"

namespace epona::test {

inline std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

inline bool contains(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

}  // namespace epona::test
