// apps/epona/cli.hpp — the `epona` program as a function: picks the subcommand, parses its
// options, runs it, and turns every failure into "epona: error: <message>" and exit status 1.
// Declared here and defined in apps/epona/cli.cpp, one translation unit: the program links it, and
// so do the tests that run the commands in-process with their own output streams
// (tests/CMakeLists.txt builds it once for all of them, where each used to compile every command).
#pragma once

#include <filesystem>
#include <ostream>
#include <string>
#include <vector>

#include "activity.hpp"
#include "epona/core/printable.hpp"

namespace epona::app {

inline constexpr const char* kVersion = "0.1.0";

// Runs the program on `args` (without argv[0]). `interactive`: err is a terminal.
int run(const std::vector<std::string>& args, std::ostream& out, std::ostream& err, bool interactive = false);

// The one error line: escaped (no control characters from echoed input reach the terminal) and
// cut (a message never echoes megabytes); newlines the program wrote itself are kept.
inline int fail_line(std::ostream& err, const std::string& message) {
  err << "epona: error: " << printable(message, 4000, true) << "\n";
  current_activity().clear();
  return 1;
}

// "<activity>: cannot create folder 'a/b/c': Not a directory" rather than the library's text.
inline std::string filesystem_text(const std::filesystem::filesystem_error& e) {
  std::string s = current_activity() + ": " + e.code().message();
  if (!e.path1().empty()) s += ": '" + e.path1().string() + "'";
  if (!e.path2().empty()) s += " -> '" + e.path2().string() + "'";
  return s;
}

}  // namespace epona::app
