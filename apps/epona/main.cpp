// apps/epona/main.cpp — the `epona` command-line program (see apps/epona/cli.hpp and docs/cli.md).
#include <unistd.h>

#include <iostream>
#include <string>
#include <vector>

#include "epona/cli.hpp"         // apps/epona/cli.hpp
#include "epona/interrupts.hpp"  // apps/epona/interrupts.hpp

// The one translation unit that compiles stb (PNG/JPEG decoding, PNG encoding). Included last:
// stb_image.h compiles its implementation on every inclusion while the macro is defined.
#include "epona/io/stb_implementation.hpp"

int main(int argc, char** argv) {
  epona::app::install_interrupt_handlers();
  const std::vector<std::string> args(argv + 1, argv + argc);
  return epona::app::run(args, std::cout, std::cerr, isatty(STDERR_FILENO) != 0);
}
