// epona/core/env.hpp — on/off settings read from the environment (the backends' switches that
// keep a fused or tuned path comparable with the plain one): unset or empty gives the default,
// "1" on, "0" off, anything else an epona::Error naming the variable.
#pragma once

#include <cstdlib>
#include <cstring>

#include "epona/core/error.hpp"

namespace epona {

inline bool env_flag(const char* name, bool fallback) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  if (std::strcmp(v, "1") == 0) return true;
  if (std::strcmp(v, "0") == 0) return false;
  fail(name, " must be 0 or 1, got '", v, "'");
}

}  // namespace epona
