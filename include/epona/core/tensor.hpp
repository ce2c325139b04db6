// epona/core/tensor.hpp — a dense, row-major (C-contiguous) n-d array in PyTorch dimension
// order. A Tensor either owns its storage (shared, so copies are cheap handles) or is a
// view of memory owned elsewhere (an arena, a memory-mapped file). Shapes are checked on
// every reshape/slice; element access by index is for host tensors and tests.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <initializer_list>
#include <memory>
#include <numeric>
#include <sstream>
#include <string>
#include <vector>

#include "epona/core/backend.hpp"
#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"

namespace epona {

using Shape = std::vector<std::int64_t>;

inline std::string shape_str(const Shape& s) {
  std::ostringstream os;
  os << '(';
  for (std::size_t i = 0; i < s.size(); ++i) os << (i ? ", " : "") << s[i];
  if (s.size() == 1) os << ',';
  os << ')';
  return os.str();
}

// Number of elements; throws on negative extents or int64 overflow (hostile headers).
inline std::int64_t shape_numel(const Shape& s) {
  std::int64_t n = 1;
  for (auto d : s) {
    EPONA_CHECK(d >= 0, "negative dimension in shape ", shape_str(s));
    EPONA_CHECK(d == 0 || n <= INT64_MAX / d, "shape ", shape_str(s), " overflows int64");
    n *= d;
  }
  return n;
}

template <class T, class B = Cpu>
class Tensor {
 public:
  using value_type = T;
  using backend = B;

  Tensor() = default;

  // Allocates an owning tensor (contents uninitialised).
  explicit Tensor(Shape shape) : shape_(std::move(shape)) {
    const auto n = shape_numel(shape_);
    // numel fits int64, but numel * sizeof(T) may not fit a size_t (2^62 floats -> 0 bytes)
    EPONA_CHECK(static_cast<std::uint64_t>(n) <= PTRDIFF_MAX / sizeof(T), "shape ", shape_str(shape_), " needs more than ",
                PTRDIFF_MAX, " bytes");
    storage_ = BackendMemory<B>::allocate(static_cast<std::size_t>(n) * sizeof(T));
    data_ = static_cast<T*>(storage_.get());
  }
  Tensor(std::initializer_list<std::int64_t> shape) : Tensor(Shape(shape)) {}

  // A non-owning view; `keepalive` (optional) holds whatever owns the memory.
  static Tensor view(T* data, Shape shape, std::shared_ptr<void> keepalive = {}) {
    Tensor t;
    shape_numel(shape);
    t.shape_ = std::move(shape);
    t.data_ = data;
    t.storage_ = std::move(keepalive);
    return t;
  }

  static Tensor zeros(Shape shape) requires is_host_backend<B> {
    Tensor t(std::move(shape));
    std::fill_n(t.data(), t.numel(), T{});
    return t;
  }
  static Tensor full(Shape shape, T value) requires is_host_backend<B> {
    Tensor t(std::move(shape));
    std::fill_n(t.data(), t.numel(), value);
    return t;
  }

  T* data() const { return data_; }
  const Shape& shape() const { return shape_; }
  int dim() const { return static_cast<int>(shape_.size()); }
  std::int64_t numel() const { return shape_.empty() && !data_ ? 0 : shape_numel(shape_); }
  std::size_t nbytes() const { return static_cast<std::size_t>(numel()) * sizeof(T); }
  bool empty() const { return data_ == nullptr; }
  const std::shared_ptr<void>& storage() const { return storage_; }

  // Extent of dimension d; negative d counts from the end like PyTorch.
  std::int64_t size(int d) const {
    const int n = dim();
    if (d < 0) d += n;
    EPONA_CHECK(d >= 0 && d < n, "dimension ", d, " out of range for shape ", shape_str(shape_));
    return shape_[static_cast<std::size_t>(d)];
  }

  // Same data, new shape; one extent may be -1 (inferred).
  Tensor reshape(Shape s) const {
    std::int64_t known = 1;
    int infer = -1;
    for (std::size_t i = 0; i < s.size(); ++i) {
      if (s[i] == -1) {
        EPONA_CHECK(infer < 0, "reshape: more than one -1 in ", shape_str(s));
        infer = static_cast<int>(i);
      } else {
        EPONA_CHECK(s[i] >= 0, "reshape: negative extent in ", shape_str(s));
        known *= s[i];
      }
    }
    if (infer >= 0) {
      EPONA_CHECK(known > 0 && numel() % known == 0, "reshape: cannot infer ", shape_str(s), " from ",
                  shape_str(shape_));
      s[static_cast<std::size_t>(infer)] = numel() / known;
    }
    EPONA_CHECK(shape_numel(s) == numel(), "reshape: ", shape_str(shape_), " has ", numel(),
                " elements, ", shape_str(s), " needs ", shape_numel(s));
    Tensor t = *this;
    t.shape_ = std::move(s);
    return t;
  }

  // Rows [begin, end) of dimension 0 (contiguous, so still a dense tensor).
  Tensor slice(std::int64_t begin, std::int64_t end) const {
    EPONA_CHECK(dim() >= 1, "slice of a 0-d tensor");
    EPONA_CHECK(0 <= begin && begin <= end && end <= shape_[0], "slice [", begin, ", ", end,
                ") out of range for shape ", shape_str(shape_));
    Tensor t = *this;
    t.shape_[0] = end - begin;
    t.data_ = data_ + begin * row_elems();
    return t;
  }

  // Sub-tensor i of dimension 0 (rank drops by one).
  Tensor operator[](std::int64_t i) const {
    EPONA_CHECK(dim() >= 1 && i >= 0 && i < shape_[0], "index ", i, " out of range for shape ",
                shape_str(shape_));
    Tensor t = *this;
    t.shape_.erase(t.shape_.begin());
    t.data_ = data_ + i * row_elems();
    return t;
  }

  // Host element access with bounds checks (tests, small tensors).
  template <class... I>
  T& at(I... idx) const requires is_host_backend<B> {
    const std::int64_t ix[] = {static_cast<std::int64_t>(idx)...};
    EPONA_CHECK(sizeof...(I) == shape_.size(), "at(): ", sizeof...(I), " indices for shape ",
                shape_str(shape_));
    std::int64_t off = 0;
    for (std::size_t d = 0; d < sizeof...(I); ++d) {
      EPONA_CHECK(ix[d] >= 0 && ix[d] < shape_[d], "at(): index ", ix[d], " out of range in dim ", d,
                  " of ", shape_str(shape_));
      off = off * shape_[d] + ix[d];
    }
    return data_[off];
  }

  // Deep copy (host backends; device copies live in the backend).
  Tensor clone() const requires is_host_backend<B> {
    Tensor t(shape_);
    if (numel()) std::memcpy(t.data(), data_, nbytes());
    return t;
  }

 private:
  std::int64_t row_elems() const {
    std::int64_t n = 1;
    for (std::size_t d = 1; d < shape_.size(); ++d) n *= shape_[d];
    return n;
  }

  std::shared_ptr<void> storage_;
  T* data_ = nullptr;
  Shape shape_;
};

template <class T, class B>
void check_shape(const Tensor<T, B>& t, const Shape& expected, const char* what) {
  EPONA_CHECK(t.shape() == expected, what, ": expected shape ", shape_str(expected), ", got ",
              shape_str(t.shape()));
}

}  // namespace epona
