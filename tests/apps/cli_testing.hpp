// What the tests of the `epona` program share: running it in-process (apps/epona/cli.hpp) with
// captured stdout and stderr, and looking for text in them.
#pragma once

#include <doctest/doctest.h>

#include <cstddef>
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

// A refused command: exit status 1 and an "epona: error: " line naming `part` that starts a line and
// ends the output (notes may come first), short and without terminal escapes.
inline void check_cli_error(const CliResult& r, const std::string& part) {
  INFO("stderr: " << r.err);
  CHECK(r.rc == 1);
  const std::size_t at = r.err.find("epona: error: ");
  REQUIRE(at != std::string::npos);
  CHECK((at == 0 || r.err[at - 1] == '\n'));
  CHECK(r.err.back() == '\n');
  CHECK(has(r.err, part));
  CHECK(r.err.size() < 5000);
  CHECK(r.err.find('\x1b') == std::string::npos);
}

}  // namespace epona::test
