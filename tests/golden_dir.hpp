// The golden set's folder: $EPONA_GOLDEN_DIR (tests/CMakeLists.txt points it at tests/data/trained
// for the trained model's runs), else the copy in tests/data/golden.
#pragma once

#include <cstdlib>
#include <string>

namespace epona::test {

inline std::string golden_dir() {
  const char* env = std::getenv("EPONA_GOLDEN_DIR");
  return env && *env ? std::string(env) : std::string(EPONA_GOLDEN_DEFAULT_DIR);
}

}  // namespace epona::test
