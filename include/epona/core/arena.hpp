// epona/core/arena.hpp — a bump allocator over one backend allocation: activations of a
// forward pass are carved out of it and released all at once, so a sampler loop allocates
// nothing (the precondition for capturing it in a CUDA graph). ArenaCounter walks the same
// allocation sequence without memory, which is how a model sizes its arena from a config.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <utility>

#include "epona/core/backend.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"

namespace epona {

// Every block starts on a 64-byte boundary (a cache line, a full AVX-512 register).
inline constexpr std::size_t arena_alignment = 64;

inline std::size_t arena_round_up(std::size_t bytes) {
  return (bytes + arena_alignment - 1) / arena_alignment * arena_alignment;
}

template <class T>
std::size_t arena_bytes_for(const Shape& shape) {
  return arena_round_up(static_cast<std::size_t>(shape_numel(shape)) * sizeof(T));
}

// Counts the bytes an allocation sequence needs; hands out shape-only (data-less) tensors,
// so the same "plan buffers" code sizes the arena and later fills it.
template <class B>
class ArenaCounter {
 public:
  template <class T>
  Tensor<T, B> take(const Shape& shape) {
    used_ += arena_bytes_for<T>(shape);
    Tensor<T, B> t = Tensor<T, B>::view(nullptr, shape);
    return t;
  }
  std::size_t bytes() const { return used_; }

 private:
  std::size_t used_ = 0;
};

template <class B>
class Arena {
 public:
  Arena() = default;
  explicit Arena(std::size_t bytes) { reserve(bytes); }
  // One owner of the buffer: a copy would hand out the same bytes twice.
  Arena(const Arena&) = delete;
  Arena& operator=(const Arena&) = delete;
  Arena(Arena&& o) noexcept { *this = std::move(o); }
  Arena& operator=(Arena&& o) noexcept {
    storage_ = std::move(o.storage_);
    base_ = std::exchange(o.base_, nullptr);
    capacity_ = std::exchange(o.capacity_, 0);
    used_ = std::exchange(o.used_, 0);
    high_water_ = std::exchange(o.high_water_, 0);
    return *this;
  }

  // Makes the capacity at least `bytes`. Only when nothing is allocated (a bigger buffer
  // replaces the old one; views handed out earlier keep the old one alive).
  void reserve(std::size_t bytes) {
    EPONA_CHECK(used_ == 0, "arena: reserve(", bytes, ") while ", used_, " bytes are in use");
    if (bytes <= capacity_) return;
    storage_ = BackendMemory<B>::allocate(bytes);
    base_ = static_cast<std::byte*>(storage_.get());
    capacity_ = bytes;
  }

  // A view of `shape` elements of T; throws (naming the request) when the arena is full,
  // which means the caller's sizing plan and its allocation sequence disagree.
  template <class T>
  Tensor<T, B> take(const Shape& shape) {
    const std::size_t need = arena_bytes_for<T>(shape);
    EPONA_CHECK(used_ + need <= capacity_, "workspace arena exhausted: a tensor of shape ", shape_str(shape),
                " needs ", need, " bytes, ", capacity_ - used_, " of ", capacity_, " are free");
    T* p = reinterpret_cast<T*>(base_ + used_);
    used_ += need;
    if (used_ > high_water_) high_water_ = used_;
    return Tensor<T, B>::view(p, shape, storage_);
  }

  std::size_t mark() const { return used_; }
  void rewind(std::size_t mark) {
    EPONA_CHECK(mark <= used_, "arena: rewind to ", mark, " beyond the current use ", used_);
    used_ = mark;
  }
  void reset() { used_ = 0; }

  std::size_t capacity() const { return capacity_; }
  std::size_t used() const { return used_; }
  std::size_t high_water() const { return high_water_; }

 private:
  std::shared_ptr<void> storage_;
  std::byte* base_ = nullptr;
  std::size_t capacity_ = 0;
  std::size_t used_ = 0;
  std::size_t high_water_ = 0;
};

// Releases everything taken from `arena` inside a scope (stack discipline).
template <class B>
class ArenaScope {
 public:
  explicit ArenaScope(Arena<B>& arena) : arena_(arena), mark_(arena.mark()) {}
  ~ArenaScope() {
    if (mark_ <= arena_.mark()) arena_.rewind(mark_);  // never throw from a destructor
  }
  ArenaScope(const ArenaScope&) = delete;
  ArenaScope& operator=(const ArenaScope&) = delete;

 private:
  Arena<B>& arena_;
  std::size_t mark_;
};

}  // namespace epona
