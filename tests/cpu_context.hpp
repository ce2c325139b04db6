// One CPU context per test program, made on first use: its thread pool and scratch are shared by
// the test cases instead of being made per case.
#pragma once

#include "epona/cpu/context.hpp"

namespace epona::test {

inline cpu::Context& cpu_context() {
  static cpu::Context context;
  return context;
}

}  // namespace epona::test
