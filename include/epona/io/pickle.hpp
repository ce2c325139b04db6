// epona/io/pickle.hpp — a restricted unpickler for the data.pkl that torch.save writes (Python's
// pickle protocol 2; harmless opcodes of protocols 3-5 too): dicts, lists, tuples, scalars, strings
// and tensors rebuilt from persistent storage ids, as torch.load(weights_only=True) would see them.
// Only the globals of a state dict are accepted, by name, and never imported or called; any other
// global is refused. Stack, marks, memo, object count and nesting are bounded, and no opcode can
// jump, so a hostile pickle fails with an epona::Error in time linear in its size.
#pragma once

#include <algorithm>
#include <bit>
#include <cctype>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/printable.hpp"
#include "epona/core/tensor.hpp"

namespace epona::io::pickle {

enum class Kind : std::uint8_t { None, Bool, Int, Float, String, Tuple, List, Dict, Global, Storage, Tensor };

inline std::string_view kind_name(Kind k) {
  switch (k) {
    case Kind::None: return "None";
    case Kind::Bool: return "bool";
    case Kind::Int: return "int";
    case Kind::Float: return "float";
    case Kind::String: return "str";
    case Kind::Tuple: return "tuple";
    case Kind::List: return "list";
    case Kind::Dict: return "dict";
    case Kind::Global: return "global";
    case Kind::Storage: return "storage";
    case Kind::Tensor: return "tensor";
  }
  return "?";
}

// A pickled value: scalars inline; strings, containers, globals, storages and tensors are an
// index into the tables of their Document (so sharing through the memo keeps identity).
struct Value {
  Kind kind = Kind::None;
  std::int64_t i = 0;  // Bool/Int value, or the table index of every other kind but Float
  double f = 0;        // Float value
};

// The only callables a checkpoint may name.
enum class Callable : std::uint8_t {
  OrderedDict,                // collections.OrderedDict
  RebuildTensorV2,            // torch._utils._rebuild_tensor_v2
  RebuildTensor,              // torch._utils._rebuild_tensor (older writers, same first 4 args)
  RebuildParameter,           // torch._utils._rebuild_parameter
  RebuildParameterWithState,  // torch._utils._rebuild_parameter_with_state
  StorageType,                // torch.FloatStorage etc.: only inside a persistent id
};

struct GlobalRef {
  Callable callable;
  DType storage_dtype = DType::F32;  // for StorageType
  std::string name;                  // "module.name", for messages
};

// A storage named by a persistent id ('storage', type, key, location, numel): its bytes are the
// archive record "<archive>/data/<key>".
struct StorageRef {
  DType dtype = DType::F32;
  std::string key;
  std::string location;
  std::int64_t numel = 0;
};

// A tensor as torch._utils._rebuild_tensor_v2 describes it (a view of a storage).
struct TensorRef {
  std::int64_t storage = 0;  // index into the storage table
  std::int64_t offset = 0;   // in elements
  Shape shape;
  Shape stride;  // in elements
  std::size_t pickle_offset = 0;
};

struct Sequence {
  std::vector<Value> items;
  std::size_t depth = 1;
};

// A dict key by value, in constant size: strings are interned when read (equal text, one index),
// so a key is its kind and one 64-bit word. Copying and hashing whole key texts per SETITEM made
// a 2 MB pickle of one long key set many times take minutes and 3.4 GB.
struct DictKey {
  char kind = 'n';  // 's' interned string, 'i' integer (and integral float, bool), 'f' other float, 'n' None
  std::uint64_t bits = 0;
  bool operator==(const DictKey&) const = default;
};
struct DictKeyHash {
  std::size_t operator()(const DictKey& k) const {
    return std::hash<std::uint64_t>()(k.bits * 0x9e3779b97f4a7c15ull + static_cast<unsigned char>(k.kind));
  }
};

struct Dict {
  std::vector<std::pair<Value, Value>> items;                  // insertion order, as Python dicts
  std::unordered_map<DictKey, std::size_t, DictKeyHash> index;  // key -> position in items
  std::size_t depth = 1;
};

// Work done on key and string text (bytes hashed or compared), for the linearity tests: it must
// stay within a small multiple of the pickle's size whatever the pickle repeats.
struct Work {
  std::uint64_t text_bytes = 0;
};

struct Limits {
  std::size_t max_stack = std::size_t{1} << 20;  // values on the unpickling stack
  std::size_t max_marks = 1024;                  // open MARKs
  std::size_t max_depth = 256;                   // container nesting
  // ~10 objects and memo entries per tensor: room for 400k tensors, while a hostile pickle
  // cannot make the reader hold more than a few hundred MB.
  std::uint64_t max_memo_index = std::uint64_t{1} << 22;
  std::size_t max_objects = std::size_t{1} << 22;  // strings, containers, storages, tensors
  std::size_t max_dims = 64;
};

// The unpickled object graph. Nothing in it owns anything outside itself.
class Document {
 public:
  Value root;

  const std::string& str(const Value& v) const { return strings_[index(v, Kind::String)]; }
  const std::vector<Value>& items(const Value& v) const {
    EPONA_CHECK(v.kind == Kind::Tuple || v.kind == Kind::List, "pickle: expected a tuple or list, got ",
                kind_name(v.kind));
    return sequences_[static_cast<std::size_t>(v.i)].items;
  }
  const Dict& dict(const Value& v) const { return dicts_[index(v, Kind::Dict)]; }
  const GlobalRef& global(const Value& v) const { return globals_[index(v, Kind::Global)]; }
  const StorageRef& storage(const Value& v) const { return storages_[index(v, Kind::Storage)]; }
  const StorageRef& storage(std::int64_t i) const { return storages_.at(static_cast<std::size_t>(i)); }
  const TensorRef& tensor(const Value& v) const { return tensors_[index(v, Kind::Tensor)]; }

  // The value stored under string key `key`, or nullptr (a scan: readers look up a few keys).
  const Value* find(const Dict& d, std::string_view key) const {
    for (const auto& [k, v] : d.items)
      if (k.kind == Kind::String && str(k) == key) return &v;
    return nullptr;
  }
  const Work& work() const { return work_; }

  // A short description for error messages: "str 'abc'", "int 3", "dict of 4 items", "tensor".
  std::string describe(const Value& v) const {
    switch (v.kind) {
      case Kind::String: return "str '" + printable(str(v)) + "'";
      case Kind::Int: return "int " + std::to_string(v.i);
      case Kind::Bool: return v.i ? "True" : "False";
      case Kind::Float: return "float " + std::to_string(v.f);
      case Kind::Dict: return "dict of " + std::to_string(dict(v).items.size()) + " items";
      case Kind::Tuple:
      case Kind::List: return std::string(kind_name(v.kind)) + " of " + std::to_string(items(v).size()) + " items";
      case Kind::Global: return "global " + global(v).name;
      default: return std::string(kind_name(v.kind));
    }
  }

  // Safe to put a hostile string into an error message (core/printable.hpp).
  static std::string printable(std::string_view s, std::size_t max_len = kPrintableDefault) {
    return epona::printable(s, max_len);
  }

 private:
  friend class Unpickler;
  std::size_t index(const Value& v, Kind k) const {
    EPONA_CHECK(v.kind == k, "pickle: expected a ", kind_name(k), ", got ", kind_name(v.kind));
    return static_cast<std::size_t>(v.i);
  }
  std::vector<std::string> strings_;
  std::vector<Sequence> sequences_;
  std::vector<Dict> dicts_;
  std::vector<GlobalRef> globals_;
  std::vector<StorageRef> storages_;
  std::vector<TensorRef> tensors_;
  Work work_;
};

class Unpickler {
 public:
  Unpickler(std::span<const std::byte> bytes, std::string source, Limits limits = {})
      : bytes_(bytes), source_(std::move(source)), limits_(limits) {}

  Document run() {
    for (;;) {
      EPONA_CHECK(pos_ < bytes_.size(), source_, ": pickle byte ", pos_,
                  ": the pickle ends without a STOP opcode (truncated?)");
      op_pos_ = pos_;
      if (step(u8())) break;
    }
    doc_.root = pop();
    return std::move(doc_);
  }

 private:
  // One opcode; returns true at STOP.
  bool step(std::uint8_t op) {
    switch (op) {
      case 0x80: protocol(); break;                                  // PROTO
      case 0x95: frame(); break;                                     // FRAME
      case '.': return true;                                         // STOP
      case '(': mark(); break;                                       // MARK
      case '}': push(new_dict()); break;                             // EMPTY_DICT
      case ']': push(new_sequence(Kind::List, {})); break;           // EMPTY_LIST
      case ')': push(new_sequence(Kind::Tuple, {})); break;          // EMPTY_TUPLE
      case 'X': push(new_string(u32())); break;                      // BINUNICODE
      case 0x8c: push(new_string(u8())); break;                      // SHORT_BINUNICODE
      case 0x8d: push(new_string(u64())); break;                     // BINUNICODE8
      case 'q': memo_put(u8()); break;                               // BINPUT
      case 'r': memo_put(u32()); break;                              // LONG_BINPUT
      case 0x94: memo_put(memo_.size()); break;                      // MEMOIZE
      case 'h': memo_get(u8()); break;                               // BINGET
      case 'j': memo_get(u32()); break;                              // LONG_BINGET
      case 'J': push_int(static_cast<std::int32_t>(u32())); break;   // BININT
      case 'K': push_int(u8()); break;                               // BININT1
      case 'M': push_int(u16()); break;                              // BININT2
      case 0x8a: push_int(long1()); break;                           // LONG1
      case 't': push(new_sequence(Kind::Tuple, pop_mark())); break;  // TUPLE
      case 0x85: push(new_sequence(Kind::Tuple, pop_n(1))); break;   // TUPLE1
      case 0x86: push(new_sequence(Kind::Tuple, pop_n(2))); break;   // TUPLE2
      case 0x87: push(new_sequence(Kind::Tuple, pop_n(3))); break;   // TUPLE3
      case 's': set_items(pop_n(2)); break;                          // SETITEM
      case 'u': set_items(pop_mark()); break;                        // SETITEMS
      case 'a': append(pop_n(1)); break;                             // APPEND
      case 'e': append(pop_mark()); break;                           // APPENDS
      case 0x88: push({Kind::Bool, 1}); break;                       // NEWTRUE
      case 0x89: push({Kind::Bool, 0}); break;                       // NEWFALSE
      case 'N': push({}); break;                                     // NONE
      case 'G': push_float(); break;                                 // BINFLOAT
      case 'c': global_from_lines(); break;                          // GLOBAL
      case 0x93: global_from_stack(); break;                         // STACK_GLOBAL
      case 'R': reduce(); break;                                     // REDUCE
      case 'Q': persistent_id(); break;                              // BINPERSID
      case 'b': build(); break;                                      // BUILD
      case '0': pop(); break;                                        // POP
      case '1': pop_mark(); break;                                   // POP_MARK
      case '2': push(top()); break;                                  // DUP
      default: error("unsupported pickle opcode ", opcode_str(op), " (only what torch.save writes is read)");
    }
    return false;
  }

  template <class... Args>
  [[noreturn]] void error(Args&&... args) const {
    fail(source_, ": pickle byte ", op_pos_, ": ", std::forward<Args>(args)...);
  }
  static std::string opcode_str(std::uint8_t op) {
    char buf[16];
    if (std::isprint(op))
      std::snprintf(buf, sizeof buf, "0x%02x '%c'", op, op);
    else
      std::snprintf(buf, sizeof buf, "0x%02x", op);
    return buf;
  }

  // ---- reading the byte stream (every read bounds-checked) ----
  const std::byte* take(std::uint64_t n, const char* what) {
    EPONA_CHECK(n <= bytes_.size() - pos_, source_, ": pickle byte ", op_pos_, ": ", what, " of ", n,
                " bytes runs past the end of the pickle (", bytes_.size() - pos_, " bytes left)");
    const std::byte* p = bytes_.data() + pos_;
    pos_ += static_cast<std::size_t>(n);
    return p;
  }
  template <class T>
  T read_le(const char* what) {
    T v;
    std::memcpy(&v, take(sizeof(T), what), sizeof(T));
    return v;
  }
  std::uint8_t u8() { return read_le<std::uint8_t>("an operand"); }
  std::uint16_t u16() { return read_le<std::uint16_t>("an operand"); }
  std::uint32_t u32() { return read_le<std::uint32_t>("an operand"); }
  std::uint64_t u64() { return read_le<std::uint64_t>("an operand"); }

  void protocol() {
    const auto p = u8();
    if (p > 5) error("pickle protocol ", int(p), " is not supported (0..5)");
  }
  void frame() {  // protocol 4 framing is only a read-ahead hint
    const std::uint64_t n = u64();
    if (n > bytes_.size() - pos_) error("a frame of ", n, " bytes runs past the end of the pickle");
  }

  std::int64_t long1() {
    const std::uint8_t n = u8();
    if (n > 8) error("an integer of ", int(n), " bytes does not fit in 64 bits");
    const std::byte* p = take(n, "a LONG1 integer");
    std::uint64_t v = 0;
    for (std::uint8_t k = 0; k < n; ++k) v |= std::uint64_t(std::to_integer<std::uint8_t>(p[k])) << (8 * k);
    if (n > 0 && n < 8 && (std::to_integer<std::uint8_t>(p[n - 1]) & 0x80)) v |= ~std::uint64_t{0} << (8 * n);
    return static_cast<std::int64_t>(v);
  }
  void push_int(std::int64_t v) { push({Kind::Int, v}); }
  void push_float() {
    const std::byte* p = take(8, "a float");
    std::uint64_t bits = 0;
    for (int k = 0; k < 8; ++k) bits = (bits << 8) | std::to_integer<std::uint8_t>(p[k]);  // big-endian
    push({Kind::Float, 0, std::bit_cast<double>(bits)});
  }

  // A newline-terminated GLOBAL operand, at most 256 bytes.
  std::string line() {
    const std::size_t left = bytes_.size() - pos_;
    const auto* begin = reinterpret_cast<const char*>(bytes_.data() + pos_);
    const auto* nl = static_cast<const char*>(std::memchr(begin, '\n', std::min<std::size_t>(left, 257)));
    if (!nl) error("a GLOBAL operand is unterminated or longer than 256 bytes");
    std::string s(begin, nl);
    pos_ += s.size() + 1;
    return s;
  }

  // ---- the stack ----
  void push(Value v) {
    if (stack_.size() >= limits_.max_stack) error("more than ", limits_.max_stack, " values on the pickle stack");
    stack_.push_back(v);
  }
  std::size_t fence() const { return marks_.empty() ? 0 : marks_.back(); }
  const Value& top() const {
    if (stack_.size() <= fence()) error("the pickle stack is empty (stack underflow)");
    return stack_.back();
  }
  Value pop() {
    Value v = top();
    stack_.pop_back();
    return v;
  }
  std::vector<Value> pop_n(std::size_t n) {
    if (stack_.size() - fence() < n) error("the pickle stack has fewer than ", n, " values (stack underflow)");
    std::vector<Value> v(stack_.end() - static_cast<std::ptrdiff_t>(n), stack_.end());
    stack_.resize(stack_.size() - n);
    return v;
  }
  void mark() {
    if (marks_.size() >= limits_.max_marks) error("more than ", limits_.max_marks, " nested MARKs");
    marks_.push_back(stack_.size());
  }
  std::vector<Value> pop_mark() {
    if (marks_.empty()) error("no MARK to pop to");
    const std::size_t m = marks_.back();
    marks_.pop_back();
    std::vector<Value> v(stack_.begin() + static_cast<std::ptrdiff_t>(m), stack_.end());
    stack_.resize(m);
    return v;
  }

  // ---- the memo ----
  void memo_put(std::uint64_t index) {
    if (index >= limits_.max_memo_index)
      error("memo index ", index, " is beyond the limit ", limits_.max_memo_index);
    memo_[index] = top();
  }
  void memo_get(std::uint64_t index) {
    auto it = memo_.find(index);
    if (it == memo_.end()) error("memo index ", index, " was never stored");
    push(it->second);
  }

  // ---- objects ----
  void count_object() {
    if (++objects_ > limits_.max_objects) error("the pickle creates more than ", limits_.max_objects, " objects");
  }
  // Equal texts share one entry (strings are immutable): a dict key is then its index, and a text
  // repeated through the pickle is stored once. Hashing here reads each input byte once.
  Value new_string(std::uint64_t length) {
    const std::byte* p = take(length, "a string");
    const std::string_view text(reinterpret_cast<const char*>(p), static_cast<std::size_t>(length));
    doc_.work_.text_bytes += text.size();
    if (auto it = interned_.find(text); it != interned_.end()) return {Kind::String, it->second};
    count_object();
    doc_.strings_.emplace_back(text);
    const auto index = static_cast<std::int64_t>(doc_.strings_.size() - 1);
    interned_.emplace(text, index);  // views the input, which outlives the unpickler
    return {Kind::String, index};
  }
  Value new_dict() {
    count_object();
    doc_.dicts_.emplace_back();
    return {Kind::Dict, static_cast<std::int64_t>(doc_.dicts_.size() - 1)};
  }
  Value new_sequence(Kind kind, std::vector<Value> items) {
    count_object();
    Sequence s{std::move(items), 1};
    for (const Value& v : s.items) s.depth = std::max(s.depth, nested_depth(v));
    doc_.sequences_.push_back(std::move(s));
    return {kind, static_cast<std::int64_t>(doc_.sequences_.size() - 1)};
  }
  // Depth of a container holding v; containers grow deeper as items are added.
  std::size_t nested_depth(const Value& v) const {
    std::size_t d = 1;
    if (v.kind == Kind::Tuple || v.kind == Kind::List)
      d = doc_.sequences_[std::size_t(v.i)].depth;
    else if (v.kind == Kind::Dict)
      d = doc_.dicts_[std::size_t(v.i)].depth;
    else
      return 2;
    if (d + 1 > limits_.max_depth) error("objects nested deeper than ", limits_.max_depth, " levels");
    return d + 1;
  }

  // Python dict keys compare by value; only the hashable scalars are supported. Constant work:
  // strings are interned, so equal texts have equal indices.
  DictKey dict_key(const Value& k) const {
    switch (k.kind) {
      case Kind::String: return {'s', std::uint64_t(k.i)};
      case Kind::Int:
      case Kind::Bool: return {'i', std::uint64_t(k.i)};
      case Kind::None: return {'n', 0};
      case Kind::Float:
        if (std::abs(k.f) < 9.0e18 && k.f == static_cast<double>(static_cast<std::int64_t>(k.f)))
          return {'i', std::uint64_t(static_cast<std::int64_t>(k.f))};
        return {'f', std::bit_cast<std::uint64_t>(k.f)};
      default: error("a dict key of type ", kind_name(k.kind), " is not supported");
    }
  }
  void set_items(const std::vector<Value>& kv) {
    if (kv.size() % 2) error("SETITEMS with an odd number (", kv.size(), ") of keys and values");
    const Value& target = top();
    if (target.kind != Kind::Dict) error("SETITEM(S) on a ", kind_name(target.kind), ", expected a dict");
    Dict& d = doc_.dicts_[std::size_t(target.i)];
    for (std::size_t n = 0; n < kv.size(); n += 2) {
      d.depth = std::max({d.depth, nested_depth(kv[n]), nested_depth(kv[n + 1])});
      auto [it, inserted] = d.index.emplace(dict_key(kv[n]), d.items.size());
      if (inserted)
        d.items.emplace_back(kv[n], kv[n + 1]);
      else
        d.items[it->second].second = kv[n + 1];
    }
  }
  void append(const std::vector<Value>& values) {
    const Value& target = top();
    if (target.kind != Kind::List) error("APPEND(S) on a ", kind_name(target.kind), ", expected a list");
    Sequence& s = doc_.sequences_[std::size_t(target.i)];
    for (const Value& v : values) {
      s.depth = std::max(s.depth, nested_depth(v));
      s.items.push_back(v);
    }
  }

  // ---- globals: looked up by name in a fixed table, never imported ----
  void global_from_lines() {
    std::string module = line();
    std::string name = line();
    push(resolve_global(module, name));
  }
  void global_from_stack() {
    const Value name = pop(), module = pop();
    if (name.kind != Kind::String || module.kind != Kind::String) error("STACK_GLOBAL needs two strings");
    push(resolve_global(doc_.strings_[std::size_t(module.i)], doc_.strings_[std::size_t(name.i)]));
  }
  Value resolve_global(const std::string& module, const std::string& name) {
    const std::string full = module + "." + name;
    GlobalRef g{Callable::OrderedDict, DType::F32, full};
    if (full == "collections.OrderedDict")
      g.callable = Callable::OrderedDict;
    else if (full == "torch._utils._rebuild_tensor_v2")
      g.callable = Callable::RebuildTensorV2;
    else if (full == "torch._utils._rebuild_tensor")
      g.callable = Callable::RebuildTensor;
    else if (full == "torch._utils._rebuild_parameter")
      g.callable = Callable::RebuildParameter;
    else if (full == "torch._utils._rebuild_parameter_with_state")
      g.callable = Callable::RebuildParameterWithState;
    else if (module == "torch" && storage_dtype(name, g.storage_dtype))
      g.callable = Callable::StorageType;
    else if (module == "torch" && name.size() > 7 && name.ends_with("Storage"))
      error("unsupported storage type '", Document::printable(full),
            "' (supported: FloatStorage, BFloat16Storage, HalfStorage, LongStorage)");
    else
      error("refusing to load: the pickle asks for global '", Document::printable(full),
            "' (only collections.OrderedDict, torch._utils._rebuild_* and torch.*Storage are allowed)");
    count_object();
    doc_.globals_.push_back(std::move(g));
    return {Kind::Global, static_cast<std::int64_t>(doc_.globals_.size() - 1)};
  }
  static bool storage_dtype(const std::string& name, DType& dtype) {
    if (name == "FloatStorage")
      dtype = DType::F32;
    else if (name == "BFloat16Storage")
      dtype = DType::BF16;
    else if (name == "HalfStorage")
      dtype = DType::F16;
    else if (name == "LongStorage")
      dtype = DType::I64;
    else
      return false;
    return true;
  }

  // ---- REDUCE: the allowed callables, interpreted (nothing is executed) ----
  void reduce() {
    const Value args = pop(), callable = pop();
    if (callable.kind != Kind::Global) error("REDUCE on a ", kind_name(callable.kind), ", expected a global");
    if (args.kind != Kind::Tuple) error("REDUCE with ", kind_name(args.kind), " arguments, expected a tuple");
    const GlobalRef& g = doc_.globals_[std::size_t(callable.i)];
    const std::vector<Value> a = doc_.sequences_[std::size_t(args.i)].items;  // copy: tables may grow
    switch (g.callable) {
      case Callable::OrderedDict:
        if (!a.empty()) error("collections.OrderedDict called with arguments (only OrderedDict() is supported)");
        push(new_dict());
        break;
      case Callable::RebuildTensorV2: push(rebuild_tensor(a, g.name, 6)); break;
      case Callable::RebuildTensor: push(rebuild_tensor(a, g.name, 4)); break;
      case Callable::RebuildParameter: push(rebuild_parameter(a, g.name, 3)); break;
      case Callable::RebuildParameterWithState: push(rebuild_parameter(a, g.name, 4)); break;
      case Callable::StorageType: error(g.name, " may only appear in a persistent id, not be called");
    }
  }

  std::int64_t int_arg(const Value& v, const std::string& fn, const char* what) const {
    if (v.kind != Kind::Int || v.i < 0) error(fn, ": ", what, " must be a non-negative int");
    return v.i;
  }
  Shape int_tuple(const Value& v, const std::string& fn, const char* what) const {
    if (v.kind != Kind::Tuple) error(fn, ": ", what, " must be a tuple of ints, got ", kind_name(v.kind));
    const auto& items = doc_.sequences_[std::size_t(v.i)].items;
    if (items.size() > limits_.max_dims) error(fn, ": ", what, " has ", items.size(), " dimensions");
    Shape s;
    for (const Value& x : items) s.push_back(int_arg(x, fn, what));
    return s;
  }
  bool is_empty_or_none(const Value& v) const {
    return v.kind == Kind::None || (v.kind == Kind::Dict && doc_.dicts_[std::size_t(v.i)].items.empty());
  }

  // _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad, backward_hooks[, metadata]);
  // _rebuild_tensor(storage, storage_offset, size, stride).
  Value rebuild_tensor(const std::vector<Value>& a, const std::string& fn, std::size_t nargs) {
    const bool v2 = nargs == 6;
    if (a.size() != nargs && !(v2 && a.size() == 7)) error(fn, " called with ", a.size(), " arguments");
    if (a[0].kind != Kind::Storage)
      error(fn, ": the first argument must be a storage (persistent id), got ", kind_name(a[0].kind));
    TensorRef t;
    t.storage = a[0].i;
    t.offset = int_arg(a[1], fn, "storage_offset");
    t.shape = int_tuple(a[2], fn, "size");
    t.stride = int_tuple(a[3], fn, "stride");
    t.pickle_offset = op_pos_;
    if (t.shape.size() != t.stride.size())
      error(fn, ": size ", shape_str(t.shape), " and stride ", shape_str(t.stride), " differ in length");
    if (v2 && a[4].kind != Kind::Bool) error(fn, ": requires_grad must be a bool");
    if (v2 && a[5].kind != Kind::Dict) error(fn, ": backward_hooks must be a dict");
    if (a.size() == 7 && !is_empty_or_none(a[6]))
      error(fn, ": tensor metadata (", describe(a[6]), ") is not supported");
    count_object();
    doc_.tensors_.push_back(std::move(t));
    return {Kind::Tensor, static_cast<std::int64_t>(doc_.tensors_.size() - 1)};
  }

  // _rebuild_parameter(data, requires_grad, backward_hooks[, state]): a Parameter is its tensor.
  Value rebuild_parameter(const std::vector<Value>& a, const std::string& fn, std::size_t nargs) const {
    if (a.size() != nargs) error(fn, " called with ", a.size(), " arguments, expected ", nargs);
    if (a[0].kind != Kind::Tensor) error(fn, ": the first argument must be a tensor, got ", kind_name(a[0].kind));
    if (nargs == 4 && !is_empty_or_none(a[3]) &&
        !(a[3].kind == Kind::Tuple && doc_.sequences_[std::size_t(a[3].i)].items.empty()))
      error(fn, ": parameter state (", describe(a[3]), ") is not supported");
    return a[0];
  }
  std::string describe(const Value& v) const { return doc_.describe(v); }

  // BINPERSID: ('storage', storage_type, key, location, numel) -> a storage reference.
  void persistent_id() {
    const Value pid = pop();
    const char* expected = "expected ('storage', torch.<Type>Storage, key, location, numel)";
    if (pid.kind != Kind::Tuple) error("unsupported persistent id ", describe(pid), ": ", expected);
    const auto& a = doc_.sequences_[std::size_t(pid.i)].items;
    if (a.size() != 5 || a[0].kind != Kind::String || doc_.strings_[std::size_t(a[0].i)] != "storage" ||
        a[1].kind != Kind::Global || doc_.globals_[std::size_t(a[1].i)].callable != Callable::StorageType ||
        a[2].kind != Kind::String || a[3].kind != Kind::String || a[4].kind != Kind::Int || a[4].i < 0)
      error("unsupported persistent id (", describe(pid), "): ", expected);
    StorageRef s{doc_.globals_[std::size_t(a[1].i)].storage_dtype, doc_.strings_[std::size_t(a[2].i)],
                 doc_.strings_[std::size_t(a[3].i)], a[4].i};
    if (s.key.empty()) error("a storage with an empty key");
    // torch.save writes keys "0", "1", ... and locations "cpu", "cuda:0": a long one only copies
    // its text once per storage, which a repeated BINPERSID would multiply.
    if (s.key.size() > 256 || s.location.size() > 256)
      error("a storage key or location of ", std::max(s.key.size(), s.location.size()), " bytes (at most 256)");
    count_object();
    doc_.storages_.push_back(std::move(s));
    push({Kind::Storage, static_cast<std::int64_t>(doc_.storages_.size() - 1)});
  }

  // BUILD: only an OrderedDict's attributes (state_dict()._metadata), which a reader does not need.
  void build() {
    const Value state = pop();
    const Value& target = top();
    if (target.kind != Kind::Dict)
      error("BUILD on a ", kind_name(target.kind), " (only OrderedDict state is supported)");
    if (state.kind != Kind::None && state.kind != Kind::Dict)
      error("BUILD with a ", kind_name(state.kind), " state (only a dict of attributes is supported)");
  }

  std::span<const std::byte> bytes_;
  std::string source_;
  Limits limits_;
  std::size_t pos_ = 0, op_pos_ = 0;
  std::vector<Value> stack_;
  std::vector<std::size_t> marks_;
  std::unordered_map<std::uint64_t, Value> memo_;
  std::unordered_map<std::string_view, std::int64_t> interned_;  // text -> index in doc_.strings_
  std::size_t objects_ = 0;
  Document doc_;
};

// Unpickles `bytes` (error messages name `source`).
inline Document unpickle(std::span<const std::byte> bytes, const std::string& source, const Limits& limits = {}) {
  return Unpickler(bytes, source, limits).run();
}

}  // namespace epona::io::pickle
