// Tests for epona/core/printable.hpp: control bytes escaped, valid UTF-8 kept, C1 controls and
// malformed UTF-8 escaped, long text cut (never inside a UTF-8 sequence) with its length named.
#include <doctest/doctest.h>

#include <string>

#include "epona/core/printable.hpp"

using epona::printable;

TEST_CASE("printable escapes control characters") {
  CHECK(printable("plain name.weight") == "plain name.weight");
  CHECK(printable(std::string("a\x1b[2Jb", 6)) == "a\\x1b[2Jb");
  CHECK(printable(std::string("a\0b", 3)) == "a\\x00b");
  CHECK(printable("tab\there\nnew\rcr\x7f") == "tab\\there\\nnew\\rcr\\x7f");
  CHECK(printable("line\nnext", 80, true) == "line\nnext");  // the program's own multi-line messages
}

TEST_CASE("printable keeps valid UTF-8 and escapes C1 controls and malformed sequences") {
  CHECK(printable("caf\xc3\xa9 \xe6\x97\xa5\xe6\x9c\xac \xf0\x9f\x9a\x97") == "caf\xc3\xa9 \xe6\x97\xa5\xe6\x9c\xac \xf0\x9f\x9a\x97");
  CHECK(printable("\xc2\x9b" "31m") == "\\xc2\\x9b31m");  // U+009B is CSI on some terminals
  CHECK(printable("\xff\xfe") == "\\xff\\xfe");
  CHECK(printable("\xe6\x97") == "\\xe6\\x97");          // a cut sequence
  CHECK(printable("\xc0\xaf") == "\\xc0\\xaf");          // overlong '/'
  CHECK(printable("\xed\xa0\x80") == "\\xed\\xa0\\x80");  // a surrogate
}

TEST_CASE("printable cuts long text to a prefix and names the full length") {
  const std::string huge(30'000'000, 'A');
  const std::string p = printable(huge);
  CHECK(p.size() < 120);
  CHECK(p == std::string(80, 'A') + "... (30000000 bytes)");
  // Never inside a UTF-8 sequence: 79 ASCII bytes then a 2-byte character stops before it.
  CHECK(printable(std::string(79, 'a') + "\xc3\xa9" + "zz") == std::string(79, 'a') + "... (83 bytes)");
  // Escapes grow the output, the cut counts input bytes: at most 4x the limit.
  CHECK(printable(std::string(1000, '\x1b'), 10).size() <= 40 + 20);
}
