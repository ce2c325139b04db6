// tests/io/zip_builder.hpp — test-only ZIP writer for the reader's tests: stored or flagged-as-
// compressed entries, classic or ZIP64 headers, torch.save-style data descriptors, a comment, and
// sparse multi-GB files (zero bytes after each entry's given head are left as holes). It reports
// where every structure lies, so tests can corrupt exact fields.
#pragma once

#include <fcntl.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/io/zip.hpp"

namespace zip_test {

struct ZipSpec {
  struct Entry {
    std::string name;
    std::string data;            // the entry's first bytes
    std::uint64_t size = ~0ull;  // total size, zero-filled after `data`; default data.size()
    std::uint16_t method = 0;    // 0 stored; 8 marks it deflated (the bytes are not compressed)
    bool descriptor = false;     // bit 3: zero CRC/sizes in the local header, data descriptor after
    std::uint64_t total() const { return size == ~0ull ? data.size() : size; }
  };
  std::vector<Entry> entries;
  bool zip64 = false;  // ZIP64 extra fields in every header, ZIP64 end record and locator
  std::string comment;
};

struct ZipLayout {
  std::vector<std::pair<std::uint64_t, std::string>> chunks;  // (offset, bytes); the rest is zero
  std::uint64_t size = 0;
  std::vector<std::uint64_t> local_offsets, data_offsets, central_offsets;
  std::uint64_t cd_offset = 0, cd_size = 0, zip64_end_offset = 0, eocd_offset = 0;

  std::string bytes() const {
    std::string out(size, '\0');
    for (const auto& [off, b] : chunks) std::memcpy(out.data() + off, b.data(), b.size());
    return out;
  }
  // Writes the archive with holes where it is zero (sparse on ext4/tmpfs).
  void write_sparse(const std::string& path) const {
    const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    EPONA_CHECK(fd >= 0, path, ": cannot create");
    bool ok = ::ftruncate(fd, static_cast<off_t>(size)) == 0;
    for (const auto& [off, b] : chunks)
      ok = ok && ::pwrite(fd, b.data(), b.size(), static_cast<off_t>(off)) == static_cast<ssize_t>(b.size());
    ::close(fd);
    EPONA_CHECK(ok, path, ": cannot write the test archive");
  }
};

template <class T>
void put(std::string& s, T v) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  s.append(b, sizeof(T));
}

inline ZipLayout layout_zip(const ZipSpec& spec) {
  ZipLayout z;
  std::string central;
  std::uint64_t pos = 0;
  const std::uint32_t sat32 = 0xffffffffu;
  for (const auto& e : spec.entries) {
    const std::uint64_t size = e.total();
    const std::uint32_t crc =
        size == e.data.size()
            ? epona::io::crc32({reinterpret_cast<const std::byte*>(e.data.data()), e.data.size()})
            : 0;  // sparse entries: not verified by the tests
    const std::uint16_t flags = e.descriptor ? 0x0808 : 0x0800;
    std::string local;
    put<std::uint32_t>(local, 0x04034b50);
    put<std::uint16_t>(local, spec.zip64 ? 45 : 20);
    put<std::uint16_t>(local, flags);
    put<std::uint16_t>(local, e.method);
    put<std::uint16_t>(local, 0);
    put<std::uint16_t>(local, 0x21);
    std::string extra;
    if (spec.zip64 && !e.descriptor) {
      put<std::uint16_t>(extra, 1);
      put<std::uint16_t>(extra, 16);
      put<std::uint64_t>(extra, size);
      put<std::uint64_t>(extra, size);
    }
    put<std::uint32_t>(local, e.descriptor ? 0 : crc);
    put<std::uint32_t>(local, e.descriptor ? 0 : spec.zip64 ? sat32 : static_cast<std::uint32_t>(size));
    put<std::uint32_t>(local, e.descriptor ? 0 : spec.zip64 ? sat32 : static_cast<std::uint32_t>(size));
    put<std::uint16_t>(local, static_cast<std::uint16_t>(e.name.size()));
    put<std::uint16_t>(local, static_cast<std::uint16_t>(extra.size()));
    local += e.name + extra;
    z.local_offsets.push_back(pos);
    z.data_offsets.push_back(pos + local.size());
    local += e.data;
    z.chunks.emplace_back(pos, local);
    pos += local.size() + (size - e.data.size());
    if (e.descriptor) {
      std::string dd;
      put<std::uint32_t>(dd, 0x08074b50);
      put<std::uint32_t>(dd, crc);
      if (spec.zip64) {
        put<std::uint64_t>(dd, size);
        put<std::uint64_t>(dd, size);
      } else {
        put<std::uint32_t>(dd, static_cast<std::uint32_t>(size));
        put<std::uint32_t>(dd, static_cast<std::uint32_t>(size));
      }
      z.chunks.emplace_back(pos, dd);
      pos += dd.size();
    }
    // central directory record
    z.central_offsets.push_back(central.size());
    std::string cextra;
    if (spec.zip64) {
      put<std::uint16_t>(cextra, 1);
      put<std::uint16_t>(cextra, 24);
      put<std::uint64_t>(cextra, size);
      put<std::uint64_t>(cextra, size);
      put<std::uint64_t>(cextra, z.local_offsets.back());
    }
    put<std::uint32_t>(central, 0x02014b50);
    put<std::uint16_t>(central, spec.zip64 ? 45 : 20);
    put<std::uint16_t>(central, spec.zip64 ? 45 : 20);
    put<std::uint16_t>(central, flags);
    put<std::uint16_t>(central, e.method);
    put<std::uint16_t>(central, 0);
    put<std::uint16_t>(central, 0x21);
    put<std::uint32_t>(central, crc);
    put<std::uint32_t>(central, spec.zip64 ? sat32 : static_cast<std::uint32_t>(size));
    put<std::uint32_t>(central, spec.zip64 ? sat32 : static_cast<std::uint32_t>(size));
    put<std::uint16_t>(central, static_cast<std::uint16_t>(e.name.size()));
    put<std::uint16_t>(central, static_cast<std::uint16_t>(cextra.size()));
    put<std::uint16_t>(central, 0);
    put<std::uint16_t>(central, 0);
    put<std::uint16_t>(central, 0);
    put<std::uint32_t>(central, 0);
    put<std::uint32_t>(central, spec.zip64 ? sat32 : static_cast<std::uint32_t>(z.local_offsets.back()));
    central += e.name + cextra;
  }
  z.cd_offset = pos;
  z.cd_size = central.size();
  for (auto& off : z.central_offsets) off += pos;
  z.chunks.emplace_back(pos, central);
  pos += central.size();
  const std::uint64_t n = spec.entries.size();
  std::string end;
  if (spec.zip64) {
    z.zip64_end_offset = pos;
    put<std::uint32_t>(end, 0x06064b50);
    put<std::uint64_t>(end, 44);
    put<std::uint16_t>(end, 45);
    put<std::uint16_t>(end, 45);
    put<std::uint32_t>(end, 0);
    put<std::uint32_t>(end, 0);
    put<std::uint64_t>(end, n);
    put<std::uint64_t>(end, n);
    put<std::uint64_t>(end, z.cd_size);
    put<std::uint64_t>(end, z.cd_offset);
    put<std::uint32_t>(end, 0x07064b50);
    put<std::uint32_t>(end, 0);
    put<std::uint64_t>(end, z.zip64_end_offset);
    put<std::uint32_t>(end, 1);
  }
  z.eocd_offset = pos + end.size();
  put<std::uint32_t>(end, 0x06054b50);
  put<std::uint16_t>(end, 0);
  put<std::uint16_t>(end, 0);
  put<std::uint16_t>(end, spec.zip64 ? 0xffff : static_cast<std::uint16_t>(n));
  put<std::uint16_t>(end, spec.zip64 ? 0xffff : static_cast<std::uint16_t>(n));
  put<std::uint32_t>(end, spec.zip64 ? sat32 : static_cast<std::uint32_t>(z.cd_size));
  put<std::uint32_t>(end, spec.zip64 ? sat32 : static_cast<std::uint32_t>(z.cd_offset));
  put<std::uint16_t>(end, static_cast<std::uint16_t>(spec.comment.size()));
  end += spec.comment;
  z.chunks.emplace_back(pos, end);
  z.size = pos + end.size();
  return z;
}

// Little-endian field patching for corruption tests.
template <class T>
void poke(std::string& bytes, std::uint64_t offset, T v) {
  std::memcpy(bytes.data() + offset, &v, sizeof(T));
}

// An in-memory archive over `bytes` (which must outlive it).
inline epona::io::ZipArchive open_zip(const std::string& bytes, const std::string& name = "test.zip") {
  return epona::io::ZipArchive({reinterpret_cast<const std::byte*>(bytes.data()), bytes.size()}, nullptr, name);
}

}  // namespace zip_test
