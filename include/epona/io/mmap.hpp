// epona/io/mmap.hpp — a read-only memory mapping of a whole file (POSIX mmap), held by a
// shared_ptr so that tensors viewing the file keep it mapped; unmapped when the last holder
// goes. Opening reports missing files, directories, empty files and OS errors by name.
#pragma once

#include <cerrno>
#include <cstddef>
#include <cstring>
#include <memory>
#include <span>
#include <string>

#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include "epona/core/error.hpp"
#include "epona/io/read_only_file.hpp"

namespace epona::io {

class MappedFile {
 public:
  // Maps `path` read-only. Throws epona::Error naming the file and the reason.
  static std::shared_ptr<const MappedFile> open(const std::string& path) {
    const ReadOnlyFile file(path);  // closed on return: the mapping stays valid after close
    const struct stat& st = file.status();
    if (!S_ISREG(st.st_mode)) fail(path, ": not a regular file");
    if (st.st_size == 0) fail(path, ": empty file (0 bytes)");
    const auto size = static_cast<std::size_t>(st.st_size);
    void* p = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE, file.fd(), 0);
    if (p == MAP_FAILED) fail(path, ": cannot map ", size, " bytes: ", std::strerror(errno));
    return std::shared_ptr<const MappedFile>(new MappedFile(path, static_cast<const std::byte*>(p), size));
  }

  MappedFile(const MappedFile&) = delete;
  MappedFile& operator=(const MappedFile&) = delete;
  ~MappedFile() { ::munmap(const_cast<std::byte*>(data_), size_); }

  std::span<const std::byte> bytes() const { return {data_, size_}; }
  std::size_t size() const { return size_; }
  const std::string& path() const { return path_; }

 private:
  MappedFile(std::string path, const std::byte* data, std::size_t size)
      : path_(std::move(path)), data_(data), size_(size) {}

  std::string path_;
  const std::byte* data_;
  std::size_t size_;
};

}  // namespace epona::io
