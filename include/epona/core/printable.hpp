// epona/core/printable.hpp — text from a file or the command line made safe to print: control
// characters (ESC, NUL, C1 controls, invalid UTF-8) become visible escapes, so a tensor name
// cannot drive the terminal, and long text is cut to a prefix, so an error never echoes
// megabytes of input. Every error or listing that shows user input goes through printable().
#pragma once

#include <cstddef>
#include <cstdio>
#include <string>
#include <string_view>

namespace epona {

namespace printable_detail {

// Length of the well-formed UTF-8 sequence at s[i] that is printable (not a C1 control, not a
// surrogate, not overlong), or 0 when the byte must be escaped.
inline std::size_t utf8_printable_length(std::string_view s, std::size_t i) {
  const auto b = [&](std::size_t k) { return static_cast<unsigned char>(s[i + k]); };
  const unsigned char c = b(0);
  std::size_t n = c >= 0xf0 && c <= 0xf4 ? 4 : c >= 0xe0 ? 3 : c >= 0xc2 && c <= 0xdf ? 2 : 0;
  if (n == 0 || c > 0xf4 || i + n > s.size()) return 0;
  for (std::size_t k = 1; k < n; ++k)
    if ((b(k) & 0xc0) != 0x80) return 0;
  if (c == 0xc2 && b(1) < 0xa0) return 0;                     // U+0080..U+009F: C1 controls (CSI is U+009B)
  if (c == 0xe0 && b(1) < 0xa0) return 0;                     // overlong
  if (c == 0xed && b(1) >= 0xa0) return 0;                    // surrogates
  if (c == 0xf0 && b(1) < 0x90) return 0;                     // overlong
  if (c == 0xf4 && b(1) >= 0x90) return 0;                    // beyond U+10FFFF
  return n;
}

inline void append_escape(std::string& out, unsigned char c) {
  switch (c) {
    case '\n': out += "\\n"; return;
    case '\r': out += "\\r"; return;
    case '\t': out += "\\t"; return;
    default: {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\x%02x", c);
      out += buf;
    }
  }
}

}  // namespace printable_detail

// Default cut for echoed input: enough to recognise a value, short enough for one line.
inline constexpr std::size_t kPrintableDefault = 80;

// `s` with every control byte and malformed UTF-8 byte escaped (\x1b, \x00, \n ...), cut after
// `max_bytes` input bytes (never inside a UTF-8 sequence) with "... (N bytes)" appended.
// `keep_newlines`: '\n' and '\t' pass through (for multi-line messages the program wrote itself).
inline std::string printable(std::string_view s, std::size_t max_bytes = kPrintableDefault,
                             bool keep_newlines = false) {
  std::string out;
  out.reserve(std::min(s.size(), max_bytes) + 8);
  std::size_t i = 0;
  while (i < s.size() && i < max_bytes) {
    const auto c = static_cast<unsigned char>(s[i]);
    if (c >= 0x20 && c < 0x7f) {
      out += static_cast<char>(c);
      ++i;
    } else if (keep_newlines && (c == '\n' || c == '\t')) {
      out += static_cast<char>(c);
      ++i;
    } else if (const std::size_t n = c >= 0x80 ? printable_detail::utf8_printable_length(s, i) : 0; n > 0) {
      if (i + n > max_bytes) break;
      out.append(s.substr(i, n));
      i += n;
    } else {
      printable_detail::append_escape(out, c);
      ++i;
    }
  }
  if (i < s.size()) out += "... (" + std::to_string(s.size()) + " bytes)";
  return out;
}

}  // namespace epona
