// What the tests of the `epona` program share: running it in-process (apps/epona/cli.hpp) with
// captured stdout and stderr, and looking for text in them.
#pragma once

#include <sstream>
#include <string>
#include <vector>

#include "../../apps/epona/cli.hpp"

namespace epona::test {

struct CliResult {
  int rc = -1;
  std::string out, err;
};

inline CliResult cli(const std::vector<std::string>& args) {
  std::ostringstream out, err;
  CliResult r;
  r.rc = app::run(args, out, err, false);
  r.out = out.str();
  r.err = err.str();
  return r;
}

inline bool has(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

}  // namespace epona::test
