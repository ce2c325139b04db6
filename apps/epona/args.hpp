// apps/epona/args.hpp — the command line of one subcommand: options declared once (long name,
// optional one-letter name, value or flag, help, default), parsed with errors that name the
// option and the command, and the --help text generated from the same declarations.
#pragma once

#include <charconv>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "epona/core/error.hpp"

namespace epona::app {

// A mistake on the command line (as opposed to a problem with the files it names).
class UsageError : public Error {
 public:
  using Error::Error;
};

template <class... A>
[[noreturn]] void usage_fail(A&&... parts) {
  throw UsageError(epona::detail::concat(std::forward<A>(parts)...));
}

struct OptionSpec {
  std::string name;        // without the leading "--"
  char short_name = 0;     // 0: none
  std::string value_name;  // empty: a flag
  std::string help;
  std::string default_text;  // shown in --help; empty: none
};

class ParsedArgs {
 public:
  ParsedArgs(std::string command, std::map<std::string, std::string> values, std::vector<std::string> positionals)
      : command_(std::move(command)), values_(std::move(values)), positionals_(std::move(positionals)) {}

  bool has(const std::string& name) const { return values_.count(name) != 0; }
  bool flag(const std::string& name) const { return has(name); }
  std::optional<std::string> get(const std::string& name) const {
    auto it = values_.find(name);
    return it == values_.end() ? std::nullopt : std::optional<std::string>(it->second);
  }
  std::string text(const std::string& name, const std::string& fallback) const { return get(name).value_or(fallback); }

  // An integer option in [lo, hi]; `fallback` when absent.
  std::int64_t integer(const std::string& name, std::int64_t fallback, std::int64_t lo,
                       std::int64_t hi = std::numeric_limits<std::int64_t>::max()) const {
    const auto v = get(name);
    return v ? parse_integer(*v, name, lo, hi) : fallback;
  }
  std::optional<std::int64_t> maybe_integer(const std::string& name, std::int64_t lo,
                                      std::int64_t hi = std::numeric_limits<std::int64_t>::max()) const {
    const auto v = get(name);
    if (!v) return std::nullopt;
    return parse_integer(*v, name, lo, hi);
  }
  // One of `allowed` (exact match); `fallback` when absent.
  std::string choice(const std::string& name, const std::vector<std::string>& allowed, const std::string& fallback) const {
    const auto v = get(name);
    if (!v) return fallback;
    for (const auto& a : allowed)
      if (*v == a) return a;
    std::string list;
    for (std::size_t i = 0; i < allowed.size(); ++i) list += (i ? ", " : "") + allowed[i];
    usage_fail("--", name, " must be one of ", list, "; got '", *v, "'");
  }
  const std::vector<std::string>& positionals() const { return positionals_; }
  const std::string& command() const { return command_; }

 private:
  std::int64_t parse_integer(const std::string& v, const std::string& name, std::int64_t lo, std::int64_t hi) const {
    std::int64_t out = 0;
    const char* end = v.data() + v.size();
    const auto [p, ec] = std::from_chars(v.data(), end, out);
    if (v.empty() || ec != std::errc() || p != end)
      usage_fail("--", name, " needs an integer, got '", v, "'");
    if (out < lo || out > hi) {
      if (hi == std::numeric_limits<std::int64_t>::max()) usage_fail("--", name, " must be at least ", lo, ", got ", out);
      usage_fail("--", name, " must be in [", lo, ", ", hi, "], got ", out);
    }
    return out;
  }

  std::string command_;
  std::map<std::string, std::string> values_;
  std::vector<std::string> positionals_;
};

class ArgParser {
 public:
  // `command` as typed ("epona plan"); `usage` the synopsis after it; `summary` one paragraph.
  ArgParser(std::string command, std::string usage, std::string summary)
      : command_(std::move(command)), usage_(std::move(usage)), summary_(std::move(summary)) {
    flag("help", "show this help and exit", 'h');
  }

  ArgParser& flag(std::string name, std::string help, char short_name = 0) {
    specs_.push_back({std::move(name), short_name, "", std::move(help), ""});
    return *this;
  }
  ArgParser& option(std::string name, std::string value_name, std::string help, std::string default_text = "",
                    char short_name = 0) {
    specs_.push_back({std::move(name), short_name, std::move(value_name), std::move(help), std::move(default_text)});
    return *this;
  }
  // Positional arguments: at least `min`, at most `max`; `what` names them in --help/errors.
  ArgParser& positionals(std::size_t min, std::size_t max, std::string what) {
    min_pos_ = min, max_pos_ = max, pos_what_ = std::move(what);
    return *this;
  }
  // Free text appended to --help (examples, notes).
  ArgParser& epilog(std::string text) {
    epilog_ = std::move(text);
    return *this;
  }

  // Parses `args` (without the program and command names). --help is reported through
  // ParsedArgs::flag("help") before any other check, so `cmd --help` never fails.
  ParsedArgs parse(const std::vector<std::string>& args) const {
    std::map<std::string, std::string> values;
    std::vector<std::string> pos;
    bool only_positionals = false;
    for (std::size_t i = 0; i < args.size(); ++i) {
      const std::string& a = args[i];
      if (only_positionals || a.size() < 2 || a[0] != '-' || is_negative_number(a)) {
        pos.push_back(a);
        continue;
      }
      if (a == "--") {
        only_positionals = true;
        continue;
      }
      std::string name, value;
      bool inline_value = false;
      const OptionSpec* spec = nullptr;
      if (a[1] == '-') {
        const auto eq = a.find('=');
        name = a.substr(2, eq == std::string::npos ? std::string::npos : eq - 2);
        if (eq != std::string::npos) value = a.substr(eq + 1), inline_value = true;
        spec = find(name);
      } else {
        if (a.size() != 2) usage_fail(command_, ": unknown option '", a, "' (one-letter options stand alone; see ",
                                      command_, " --help)");
        spec = find_short(a[1]);
      }
      if (!spec) usage_fail(command_, ": unknown option '", a, "' (see ", command_, " --help)");
      if (spec->name == "help") return ParsedArgs(command_, {{"help", ""}}, {});
      if (values.count(spec->name)) usage_fail(command_, ": option --", spec->name, " given more than once");
      if (spec->value_name.empty()) {
        if (inline_value) usage_fail(command_, ": option --", spec->name, " takes no value");
      } else if (!inline_value) {
        if (i + 1 >= args.size()) usage_fail(command_, ": option --", spec->name, " needs a value (", spec->value_name, ")");
        value = args[++i];
      }
      values[spec->name] = value;
    }
    if (pos.size() < min_pos_ || pos.size() > max_pos_) {
      if (max_pos_ == 0) usage_fail(command_, ": unexpected argument '", pos.front(), "' (see ", command_, " --help)");
      if (pos.size() < min_pos_) usage_fail(command_, ": missing ", pos_what_, " (see ", command_, " --help)");
      usage_fail(command_, ": too many arguments (at most ", max_pos_, " ", pos_what_, "; see ", command_, " --help)");
    }
    return ParsedArgs(command_, std::move(values), std::move(pos));
  }

  std::string help() const {
    std::ostringstream os;
    os << "usage: " << command_ << " " << usage_ << "\n\n" << summary_ << "\n\noptions:\n";
    std::size_t width = 0;
    for (const auto& s : specs_) width = std::max(width, left_column(s).size());
    for (const auto& s : specs_) {
      const std::string left = left_column(s);
      os << "  " << left << std::string(width - left.size() + 2, ' ') << s.help;
      if (!s.default_text.empty()) os << " [default: " << s.default_text << "]";
      os << "\n";
    }
    if (!epilog_.empty()) os << "\n" << epilog_ << (epilog_.back() == '\n' ? "" : "\n");
    return os.str();
  }

 private:
  static bool is_negative_number(const std::string& a) {
    return a.size() >= 2 && a[0] == '-' && (std::isdigit(static_cast<unsigned char>(a[1])) || a[1] == '.');
  }
  static std::string left_column(const OptionSpec& s) {
    std::string l = s.short_name ? std::string("-") + s.short_name + ", " : "    ";
    l += "--" + s.name;
    if (!s.value_name.empty()) l += " " + s.value_name;
    return l;
  }
  const OptionSpec* find(const std::string& name) const {
    for (const auto& s : specs_)
      if (s.name == name) return &s;
    return nullptr;
  }
  const OptionSpec* find_short(char c) const {
    for (const auto& s : specs_)
      if (s.short_name == c) return &s;
    return nullptr;
  }

  std::string command_, usage_, summary_, epilog_, pos_what_;
  std::vector<OptionSpec> specs_;
  std::size_t min_pos_ = 0, max_pos_ = 0;
};

}  // namespace epona::app
