// epona/io/tensor_map.hpp — what every weight-file reader returns: named raw tensors
// (dtype, shape, little-endian bytes) backed by memory the map keeps alive (a mapped
// file, a decompressed buffer). Layers bind from it by official parameter name and
// convert to their own dtype; lookups that fail name the key and the file.
#pragma once

#include <algorithm>
#include <cstddef>
#include <map>
#include <memory>
#include <set>
#include <span>
#include <string>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/printable.hpp"
#include "epona/core/tensor.hpp"

namespace epona::io {

struct RawTensor {
  DType dtype = DType::F32;
  Shape shape;
  std::span<const std::byte> bytes;  // exactly numel * dtype_size bytes
  std::int64_t numel() const { return shape_numel(shape); }
};

class TensorMap {
 public:
  TensorMap() = default;
  explicit TensorMap(std::string source) : source_(std::move(source)) {}

  // Adds a tensor; duplicate names and byte counts that do not match the shape are errors.
  void add(const std::string& name, RawTensor t) {
    EPONA_CHECK(!entries_.count(name), source_, ": duplicate tensor name '", printable(name, 200), "'");
    const auto n = t.numel();
    EPONA_CHECK(static_cast<std::size_t>(n) * dtype_size(t.dtype) == t.bytes.size(), source_, ": tensor '",
                name, "' of shape ", shape_str(t.shape), " and dtype ", dtype_name(t.dtype), " needs ",
                static_cast<std::size_t>(n) * dtype_size(t.dtype), " bytes, has ", t.bytes.size());
    entries_.emplace(name, std::move(t));
  }
  void keep_alive(std::shared_ptr<void> owner) { owners_.push_back(std::move(owner)); }

  bool contains(const std::string& name) const { return entries_.count(name) != 0; }
  const RawTensor& at(const std::string& name) const {
    auto it = entries_.find(name);
    EPONA_CHECK(it != entries_.end(), source_, ": missing tensor '", printable(name, 200), "'");
    return it->second;
  }
  std::vector<std::string> names() const {
    std::vector<std::string> v;
    for (auto& [k, _] : entries_) v.push_back(k);
    return v;
  }
  std::size_t size() const { return entries_.size(); }
  const std::string& source() const { return source_; }
  const std::map<std::string, RawTensor>& entries() const { return entries_; }

  // A map of the entries whose names start with `prefix`, with the prefix removed.
  TensorMap with_prefix(const std::string& prefix) const {
    TensorMap m(source_ + " [" + prefix + "*]");
    for (auto& [k, v] : entries_)
      if (k.compare(0, prefix.size(), prefix) == 0) m.entries_.emplace(k.substr(prefix.size()), v);
    m.owners_ = owners_;
    return m;
  }

  // Merges another map (names must not collide) — e.g. world-model and DC-AE files.
  void merge(const TensorMap& other) {
    for (auto& [k, v] : other.entries_) add(k, v);
    owners_.insert(owners_.end(), other.owners_.begin(), other.owners_.end());
  }

 private:
  std::string source_ = "<memory>";
  std::map<std::string, RawTensor> entries_;
  std::vector<std::shared_ptr<void>> owners_;
};

// Host tensor of type T converted from a raw tensor (float32/bfloat16/float16 sources).
template <class T>
Tensor<T, Cpu> to_tensor(const RawTensor& r) {
  Tensor<T, Cpu> t(r.shape);
  const auto n = static_cast<std::size_t>(r.numel());
  if (r.dtype == dtype_of<T>::value) {
    if (n) std::memcpy(t.data(), r.bytes.data(), n * sizeof(T));
    return t;
  }
  EPONA_CHECK(r.dtype != DType::I64, "cannot convert an int64 tensor to ", dtype_name(dtype_of<T>::value));
  for (std::size_t i = 0; i < n; ++i) t.data()[i] = T(load_as_float(r.bytes.data(), r.dtype, i));
  return t;
}

// Records which names were bound, and every missing or mis-shaped key, so that one bind
// reports all problems at once ("missing 'x', shape of 'y' is (3,) expected (4,), ...").
class BindReport {
 public:
  explicit BindReport(const TensorMap& map) : map_(map) {}

  // The raw tensor `name` if it exists with `shape`; nullptr (and a recorded problem) if not.
  const RawTensor* take(const std::string& name, const Shape& shape) {
    if (!map_.contains(name)) {
      problems_.push_back("missing '" + name + "' (expected shape " + shape_str(shape) + ")");
      return nullptr;
    }
    const RawTensor& r = map_.at(name);
    used_.insert(name);
    if (r.shape != shape) {
      problems_.push_back("'" + name + "' has shape " + shape_str(r.shape) + ", expected " + shape_str(shape));
      return nullptr;
    }
    if (r.dtype == DType::I64) {
      problems_.push_back("'" + name + "' is int64, expected a floating-point tensor");
      return nullptr;
    }
    return &r;
  }
  void problem(std::string p) { problems_.push_back(std::move(p)); }
  bool ok() const { return problems_.empty(); }
  const TensorMap& map() const { return map_; }

  // Throws if anything was missing or mis-shaped; with `strict`, also names every tensor of
  // the map that was not bound (ignoring names for which `ignore(name)` is true).
  template <class Ignore>
  void finish(bool strict, Ignore ignore) const {
    std::vector<std::string> all = problems_;
    if (strict)
      for (auto& [k, _] : map_.entries())
        if (!used_.count(k) && !ignore(k)) all.push_back("unexpected '" + k + "'");
    if (all.empty()) return;
    std::string msg = map_.source() + ": " + std::to_string(all.size()) + " weight problem(s): ";
    const std::size_t shown = std::min<std::size_t>(all.size(), 20);
    for (std::size_t i = 0; i < shown; ++i) msg += (i ? "; " : "") + all[i];
    if (shown < all.size()) msg += "; ... and " + std::to_string(all.size() - shown) + " more";
    fail(msg);
  }
  void finish(bool strict = true) const {
    finish(strict, [](const std::string&) { return false; });
  }

 private:
  const TensorMap& map_;
  std::vector<std::string> problems_;
  std::set<std::string> used_;
};

}  // namespace epona::io
