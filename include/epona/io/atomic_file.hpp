// epona/io/atomic_file.hpp — writes an output file so that it is either complete or absent: the
// bytes go to a new temporary file beside the destination, which is flushed to disk and renamed
// over the destination (atomic within a file system). The shared writer of every output format.
//
// Any failure — an exception from the caller's fill function, a short write, a full disk — removes
// the temporary file and leaves whatever was at the destination untouched. A process killed
// mid-write leaves only a "<name>.tmp-<pid>-<n>" file beside an intact destination, unless the
// program removes it from its signal handler with remove_temporary_files() (a library installs
// no handler; the epona program does, apps/epona/interrupts.hpp).
#pragma once

#include <atomic>
#include <cerrno>
#include <concepts>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include "epona/core/error.hpp"

namespace epona::io {

// Where fill functions write; buffered, every OS error reported with the destination's name.
class AtomicFileSink {
 public:
  AtomicFileSink(int fd, std::string destination) : fd_(fd), destination_(std::move(destination)) {
    buffer_.reserve(kBufferBytes);
  }
  AtomicFileSink(const AtomicFileSink&) = delete;
  AtomicFileSink& operator=(const AtomicFileSink&) = delete;

  void write(const void* data, std::size_t n) {
    const auto* p = static_cast<const char*>(data);
    if (buffer_.size() + n > kBufferBytes) flush();
    if (n >= kBufferBytes) return write_fully(p, n);  // large blocks bypass the buffer
    buffer_.insert(buffer_.end(), p, p + n);
  }
  void write(std::string_view s) { write(s.data(), s.size()); }
  std::uint64_t bytes_written() const { return written_ + buffer_.size(); }
  void flush() {
    write_fully(buffer_.data(), buffer_.size());
    buffer_.clear();
  }

 private:
  static constexpr std::size_t kBufferBytes = 1 << 16;

  void write_fully(const char* p, std::size_t n) {
    while (n > 0) {
      const ssize_t w = ::write(fd_, p, n);
      if (w < 0 && errno == EINTR) continue;
      if (w <= 0) fail(destination_, ": write failed after ", written_, " bytes: ", std::strerror(w < 0 ? errno : ENOSPC));
      p += w, n -= static_cast<std::size_t>(w), written_ += static_cast<std::uint64_t>(w);
    }
  }

  int fd_;
  std::string destination_;
  std::vector<char> buffer_;
  std::uint64_t written_ = 0;
};

namespace atomic_detail {

// The temporary files being written, in fixed slots that a signal handler can read: atomics and
// static arrays, no allocation or lock. A path too long for a slot, or a 33rd concurrent writer,
// is simply not listed (its file is left behind on a signal, as before).
struct TempRegistry {
  static constexpr int kSlots = 32;
  static constexpr std::size_t kPathBytes = 4096;
  std::atomic<int> state[kSlots];  // 0 free, 1 being filled in, 2 listed
  char path[kSlots][kPathBytes];
};
inline TempRegistry temp_registry{};  // constant-initialised: usable before main and in handlers

inline int list_temporary(const std::string& name) {
  if (name.size() >= TempRegistry::kPathBytes) return -1;
  for (int i = 0; i < TempRegistry::kSlots; ++i) {
    int free = 0;
    if (!temp_registry.state[i].compare_exchange_strong(free, 1)) continue;
    std::memcpy(temp_registry.path[i], name.c_str(), name.size() + 1);
    temp_registry.state[i].store(2);
    return i;
  }
  return -1;
}
inline void unlist_temporary(int slot) {
  if (slot >= 0) temp_registry.state[slot].store(0);
}

// A temporary file created exclusively beside `path`; removed on destruction unless released.
class TempFile {
 public:
  explicit TempFile(const std::filesystem::path& path) {
    static std::atomic<unsigned> counter{0};
    int err = 0;
    for (int attempt = 0; attempt < 100; ++attempt) {  // a stale name from a killed run is skipped
      name_ = path.string() + ".tmp-" + std::to_string(::getpid()) + "-" + std::to_string(counter++);
      // Listed before it exists: a signal between the creation and the listing left the file
      // behind (tests/apps/interrupt.cpp caught it). A signal before the creation unlinks a name
      // that is not there yet, or a stale file of a dead process of our pid.
      slot_ = list_temporary(name_);
      fd_ = ::open(name_.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
      err = errno;
      if (fd_ >= 0) return;
      unlist_temporary(slot_);
      slot_ = -1;
      if (err != EEXIST) break;
    }
    fail(path.string(), ": cannot create the temporary file ", name_, ": ", std::strerror(err));
  }
  TempFile(const TempFile&) = delete;
  TempFile& operator=(const TempFile&) = delete;
  ~TempFile() {
    unlist_temporary(slot_);
    if (fd_ >= 0) ::close(fd_);
    if (!name_.empty()) ::unlink(name_.c_str());
  }
  int fd() const { return fd_; }
  const std::string& name() const { return name_; }
  // Flushes the data to disk and closes; errors name `destination`.
  void sync_and_close(const std::string& destination) {
    const bool synced = ::fsync(fd_) == 0;
    const int err = errno;
    const bool closed = ::close(fd_) == 0;
    fd_ = -1;
    if (!synced || !closed) fail(destination, ": cannot flush the written file to disk: ", std::strerror(synced ? errno : err));
  }
  void release() {
    unlist_temporary(slot_);
    slot_ = -1;
    name_.clear();
  }

 private:
  std::string name_;
  int fd_ = -1;
  int slot_ = -1;  // in temp_registry
};

// Makes the rename itself durable (best effort: some file systems cannot sync a folder).
inline void sync_directory(const std::filesystem::path& dir) {
  const int fd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return;
  (void)::fsync(fd);
  ::close(fd);
}

}  // namespace atomic_detail

// Removes every temporary file being written now. Async-signal-safe (unlink and atomics only):
// for a program's SIGINT/SIGTERM handler, so an interrupted write leaves no "<name>.tmp-*" file.
inline void remove_temporary_files() noexcept {
  auto& r = atomic_detail::temp_registry;
  for (int i = 0; i < atomic_detail::TempRegistry::kSlots; ++i)
    if (r.state[i].load() == 2) ::unlink(r.path[i]);
}

// Creates `path` with the bytes that fill(AtomicFileSink&) writes, atomically (see above). An
// exception from fill propagates unchanged after the temporary file is removed.
template <class Fill>
  requires std::invocable<Fill&, AtomicFileSink&>
void write_atomically(const std::filesystem::path& path, Fill&& fill) {
  const std::string destination = path.string();
  std::error_code ec;
  EPONA_CHECK(!std::filesystem::is_directory(path, ec), destination, ": is a directory, cannot write a file there");
  atomic_detail::TempFile tmp(path);
  AtomicFileSink sink(tmp.fd(), destination);
  fill(sink);
  sink.flush();
  tmp.sync_and_close(destination);
  if (::rename(tmp.name().c_str(), destination.c_str()) != 0)
    fail(destination, ": cannot rename ", tmp.name(), " into place: ", std::strerror(errno));
  tmp.release();
  atomic_detail::sync_directory(path.parent_path());
}

inline void write_atomically(const std::filesystem::path& path, std::string_view bytes) {
  write_atomically(path, [&](AtomicFileSink& out) { out.write(bytes); });
}

}  // namespace epona::io
