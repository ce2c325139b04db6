// epona/io/json_reader.hpp — the one way the library reads JSON text: nlohmann's iterative SAX
// parser feeding a DOM builder that enforces the resource policy (nesting depth, value count,
// string length, duplicate keys) while it reads, in work linear in the text. And json_brief(),
// which describes a value for an error message without walking it (dump() recurses per level
// and echoes everything; a value 300k levels deep overflowed the stack).
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "epona/core/error.hpp"
#include "epona/core/printable.hpp"
#include "epona/io/limits.hpp"

namespace epona::io {

struct JsonLimits {
  int max_depth = limits::kJsonDepth;
  std::uint64_t max_values = limits::kJsonValues;
  std::uint64_t max_string_bytes = limits::kJsonStringBytes;
};

// Operations a parse performed (one per SAX event and per key lookup): the linearity tests
// count these instead of timing the parse.
struct JsonWork {
  std::uint64_t events = 0;
};

namespace json_detail {
using nlohmann::json;

class BoundedDomBuilder {
 public:
  BoundedDomBuilder(json& root, const JsonLimits& limits, JsonWork* work)
      : root_(root), limits_(limits), work_(work) {}

  bool null() { return add(json(nullptr)); }
  bool boolean(bool v) { return add(json(v)); }
  bool number_integer(json::number_integer_t v) { return add(json(v)); }
  bool number_unsigned(json::number_unsigned_t v) { return add(json(v)); }
  bool number_float(json::number_float_t v, const json::string_t&) { return add(json(v)); }
  bool string(json::string_t& v) { return check_string(v, "a string") && add(json(std::move(v))); }
  bool binary(json::binary_t&) { return refuse("binary values are not JSON text"); }
  bool start_object(std::size_t) { return open(json::value_t::object); }
  bool start_array(std::size_t) { return open(json::value_t::array); }
  bool end_object() { return close(); }
  bool end_array() { return close(); }
  bool key(json::string_t& k) {
    count();
    if (!check_string(k, "a key")) return false;
    json& object = *stack_.back();
    if (object.contains(k)) return refuse("duplicate key '" + printable(k) + "' (a JSON object keeps only one)");
    key_ = &object[std::move(k)];
    return true;
  }
  bool parse_error(std::size_t, const std::string&, const nlohmann::detail::exception& e) {
    return refuse(std::string("invalid JSON: ") + printable(e.what(), 300));
  }

  const std::string& problem() const { return problem_; }

 private:
  void count() {
    if (work_) ++work_->events;
  }
  bool refuse(std::string why) {
    if (problem_.empty()) problem_ = std::move(why);
    return false;
  }
  bool check_string(const std::string& s, const char* what) {
    if (s.size() <= limits_.max_string_bytes) return true;
    return refuse(std::string(what) + " of " + std::to_string(s.size()) + " bytes is longer than the limit of " +
                  std::to_string(limits_.max_string_bytes) + " bytes ('" + printable(s, 40) + "')");
  }
  // Places v where the document is at (the root, the next list item or the pending key's value).
  json* place(json&& v) {
    count();
    if (++values_ > limits_.max_values) {
      refuse("more than " + std::to_string(limits_.max_values) + " values (the limit for one JSON document)");
      return nullptr;
    }
    if (stack_.empty()) {
      root_ = std::move(v);
      return &root_;
    }
    json& parent = *stack_.back();
    if (parent.is_array()) {
      parent.get_ref<json::array_t&>().push_back(std::move(v));
      return &parent.get_ref<json::array_t&>().back();
    }
    *key_ = std::move(v);
    return key_;
  }
  bool add(json&& v) { return place(std::move(v)) != nullptr; }
  bool open(json::value_t type) {
    if (static_cast<int>(stack_.size()) >= limits_.max_depth)
      return refuse("nests deeper than " + std::to_string(limits_.max_depth) + " levels (the limit for JSON input)");
    json* v = place(json(type));
    if (!v) return false;
    stack_.push_back(v);
    return true;
  }
  bool close() {
    count();
    stack_.pop_back();
    return true;
  }

  json& root_;
  JsonLimits limits_;
  JsonWork* work_;
  std::vector<json*> stack_;  // open containers; a child never outlives its parent's growth
  json* key_ = nullptr;
  std::uint64_t values_ = 0;
  std::string problem_;
};

}  // namespace json_detail

// Parses `text` under `limits`; errors name `source` ("poses.json: nests deeper than 64 levels").
inline nlohmann::json parse_json(std::string_view text, const std::string& source, const JsonLimits& limits = {},
                                 JsonWork* work = nullptr) {
  nlohmann::json root;
  json_detail::BoundedDomBuilder builder(root, limits, work);
  bool ok = false;
  try {
    ok = nlohmann::json::sax_parse(text.begin(), text.end(), &builder);
  } catch (const nlohmann::json::exception& e) {
    fail(source, ": invalid JSON: ", printable(e.what(), 300));
  }
  if (!ok) fail(source, ": ", builder.problem().empty() ? std::string("invalid JSON") : builder.problem());
  return root;
}

// A value for an error message, without walking it: scalars as JSON (strings escaped and cut),
// containers by their size ("a list of 3 values").
inline std::string json_brief(const nlohmann::json& v) {
  switch (v.type()) {
    case nlohmann::json::value_t::object: return "an object of " + std::to_string(v.size()) + " key(s)";
    case nlohmann::json::value_t::array: return "a list of " + std::to_string(v.size()) + " value(s)";
    case nlohmann::json::value_t::string: return "\"" + printable(v.get_ref<const std::string&>()) + "\"";
    case nlohmann::json::value_t::binary: return "binary data";
    case nlohmann::json::value_t::discarded: return "nothing";
    default: return v.dump();  // null, booleans, numbers: no recursion, a few bytes
  }
}

}  // namespace epona::io
