// epona/io/read_only_file.hpp — a file opened read-only (POSIX), closed on destruction, with its
// status: what both the memory mapping (io/mmap.hpp) and the streamed SHA-256 (io/sha256.hpp)
// open through, so a missing file, a directory and an OS error read the same in both.
#pragma once

#include <cerrno>
#include <cstring>
#include <string>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include "epona/core/error.hpp"

namespace epona::io {

class ReadOnlyFile {
 public:
  // Opens `path`. Throws epona::Error naming the file and the reason (missing, a directory, an
  // OS error on open or stat).
  explicit ReadOnlyFile(const std::string& path) : fd_(::open(path.c_str(), O_RDONLY | O_CLOEXEC)) {
    if (fd_ < 0) {
      const int err = errno;
      if (err == ENOENT) fail(path, ": file does not exist");
      fail(path, ": cannot open: ", std::strerror(err));
    }
    if (::fstat(fd_, &status_) != 0) {
      const int err = errno;
      ::close(fd_);
      fail(path, ": cannot stat: ", std::strerror(err));
    }
    if (S_ISDIR(status_.st_mode)) {
      ::close(fd_);
      fail(path, ": is a directory, not a file");
    }
  }
  ~ReadOnlyFile() { ::close(fd_); }
  ReadOnlyFile(const ReadOnlyFile&) = delete;
  ReadOnlyFile& operator=(const ReadOnlyFile&) = delete;

  int fd() const { return fd_; }
  const struct stat& status() const { return status_; }

 private:
  int fd_;
  struct stat status_ {};
};

}  // namespace epona::io
