// epona/core/env.hpp: on/off switches from the environment — default when unset or empty,
// "1" / "0", and a clear error naming the variable for anything else.
#include "epona/core/env.hpp"

#include <doctest/doctest.h>

#include <cstdlib>
#include <string>

TEST_CASE("env_flag: default, 1, 0, and an error for anything else") {
  const char* name = "EPONA_TEST_ENV_FLAG";
  ::unsetenv(name);
  CHECK(epona::env_flag(name, true));
  CHECK_FALSE(epona::env_flag(name, false));
  ::setenv(name, "", 1);
  CHECK(epona::env_flag(name, true));
  ::setenv(name, "1", 1);
  CHECK(epona::env_flag(name, false));
  ::setenv(name, "0", 1);
  CHECK_FALSE(epona::env_flag(name, true));
  for (const char* bad : {"yes", "00", "2", " 1"}) {
    ::setenv(name, bad, 1);
    try {
      (void)epona::env_flag(name, true);
      FAIL("no error for '", bad, "'");
    } catch (const epona::Error& e) {
      const std::string what = e.what();
      CHECK(what.find(name) != std::string::npos);
      CHECK(what.find(std::string("'") + bad + "'") != std::string::npos);
    }
  }
  ::unsetenv(name);
}
