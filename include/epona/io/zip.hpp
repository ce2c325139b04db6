// epona/io/zip.hpp — a read-only ZIP reader over a memory-mapped file, for the container
// that torch.save writes (PyTorch's miniz "PyTorchStreamWriter"): stored entries only, ZIP64,
// data descriptors. Entries are returned as zero-copy views into the mapping; every offset and
// size is checked against the file before use, so a truncated or hostile archive fails cleanly.
#pragma once

#include <algorithm>
#include <array>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/printable.hpp"
#include "epona/io/mmap.hpp"

namespace epona::io {

static_assert(std::endian::native == std::endian::little,
              "the ZIP and pickle readers assume a little-endian host");

namespace zip_detail {

inline std::uint16_t le16(const std::byte* p) {
  std::uint16_t v;
  std::memcpy(&v, p, 2);
  return v;
}
inline std::uint32_t le32(const std::byte* p) {
  std::uint32_t v;
  std::memcpy(&v, p, 4);
  return v;
}
inline std::uint64_t le64(const std::byte* p) {
  std::uint64_t v;
  std::memcpy(&v, p, 8);
  return v;
}

// CRC-32 (ISO-HDLC, the ZIP checksum), slicing-by-8: ~1 byte per cycle, for optional
// verification of multi-GB records.
inline const std::array<std::array<std::uint32_t, 256>, 8>& crc32_tables() {
  static const auto tables = [] {
    std::array<std::array<std::uint32_t, 256>, 8> t{};
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[0][i] = c;
    }
    for (std::uint32_t i = 0; i < 256; ++i)
      for (std::size_t s = 1; s < 8; ++s) t[s][i] = (t[s - 1][i] >> 8) ^ t[0][t[s - 1][i] & 0xffu];
    return t;
  }();
  return tables;
}

}  // namespace zip_detail

inline std::uint32_t crc32(std::span<const std::byte> data, std::uint32_t crc = 0) {
  const auto& t = zip_detail::crc32_tables();
  std::uint32_t c = ~crc;
  const std::byte* p = data.data();
  std::size_t n = data.size();
  for (; n >= 8; n -= 8, p += 8) {
    const std::uint32_t lo = zip_detail::le32(p) ^ c;
    const std::uint32_t hi = zip_detail::le32(p + 4);
    c = t[7][lo & 0xff] ^ t[6][(lo >> 8) & 0xff] ^ t[5][(lo >> 16) & 0xff] ^ t[4][lo >> 24] ^ t[3][hi & 0xff] ^
        t[2][(hi >> 8) & 0xff] ^ t[1][(hi >> 16) & 0xff] ^ t[0][hi >> 24];
  }
  for (; n > 0; --n, ++p) c = t[0][(c ^ static_cast<std::uint8_t>(*p)) & 0xff] ^ (c >> 8);
  return ~c;
}

struct ZipEntry {
  std::string name;
  std::uint16_t method = 0;  // 0 = stored; anything else is compressed
  std::uint16_t flags = 0;
  std::uint32_t crc32 = 0;
  std::uint64_t compressed_size = 0;
  std::uint64_t size = 0;           // uncompressed
  std::uint64_t header_offset = 0;  // of the local file header
  std::uint64_t data_offset = 0;    // of the first data byte
};

class ZipArchive {
 public:
  // Maps the file and reads its central directory (every entry's local header is checked).
  static ZipArchive open(const std::string& path) {
    auto file = MappedFile::open(path);
    const auto bytes = file->bytes();
    return ZipArchive(bytes, std::move(file), path);
  }

  // An archive held in memory; `owner` keeps `bytes` alive, `name` is used in error messages.
  ZipArchive(std::span<const std::byte> bytes, std::shared_ptr<const void> owner, std::string name)
      : bytes_(bytes), owner_(std::move(owner)), name_(std::move(name)) {
    const EndRecord end = locate_end_record();
    read_central_directory(end);
    for (auto& e : entries_) check_local_header(e, end.cd_offset);
    check_no_overlap();
  }

  const std::string& name() const { return name_; }
  const std::vector<ZipEntry>& entries() const { return entries_; }
  // Whatever keeps the bytes (the mapping) alive: views returned by data() need it.
  const std::shared_ptr<const void>& owner() const { return owner_; }

  const ZipEntry* find(std::string_view entry_name) const {
    auto it = index_.find(std::string(entry_name));
    return it == index_.end() ? nullptr : &entries_[it->second];
  }
  const ZipEntry& at(std::string_view entry_name) const {
    const ZipEntry* e = find(entry_name);
    EPONA_CHECK(e != nullptr, name_, ": no entry '", entry_name, "' in the archive");
    return *e;
  }

  // The bytes of a stored entry, a view into the mapping (zero-copy).
  std::span<const std::byte> data(const ZipEntry& e) const {
    EPONA_CHECK(e.method == 0, name_, ": entry '", e.name, "' is compressed (method ", e.method,
                method_name(e.method),
                "); only stored (uncompressed) entries can be read, as torch.save writes them");
    return bytes_.subspan(e.data_offset, e.size);
  }

  // Throws if the entry's data does not match the CRC-32 of its central directory record.
  void verify_crc(const ZipEntry& e) const {
    const std::uint32_t actual = crc32(data(e));
    EPONA_CHECK(actual == e.crc32, name_, ": entry '", e.name, "' is corrupt: CRC-32 is ", hex(actual),
                ", the central directory says ", hex(e.crc32));
  }

 private:
  static constexpr std::uint32_t kLocalSig = 0x04034b50, kCentralSig = 0x02014b50, kEndSig = 0x06054b50,
                                 kZip64EndSig = 0x06064b50, kZip64LocatorSig = 0x07064b50;
  static constexpr std::uint64_t kEndSize = 22, kZip64LocatorSize = 20, kZip64EndSize = 56, kCentralSize = 46,
                                 kLocalSize = 30, kMaxComment = 65535;
  static constexpr std::uint16_t kFlagEncrypted = 1, kFlagDataDescriptor = 8;

  struct EndRecord {
    std::uint64_t entries = 0, cd_size = 0, cd_offset = 0;
    std::uint64_t cd_limit = 0;  // the central directory must end at or before this offset
  };

  static std::string hex(std::uint32_t v) {
    char buf[16];
    std::snprintf(buf, sizeof buf, "0x%08x", v);
    return buf;
  }
  static const char* method_name(std::uint16_t m) {
    switch (m) {
      case 8: return ", deflate";
      case 9: return ", deflate64";
      case 12: return ", bzip2";
      case 14: return ", lzma";
      case 93: return ", zstd";
      default: return "";
    }
  }

  // The bytes [offset, offset + length) of the file; throws (naming `what`) if out of bounds.
  const std::byte* range(std::uint64_t offset, std::uint64_t length, const std::string& what) const {
    const std::uint64_t size = bytes_.size();
    EPONA_CHECK(length <= size && offset <= size - length, name_, ": ", what, " (", length, " bytes at offset ",
                offset, ") lies outside the file of ", size, " bytes (truncated or corrupt archive)");
    return bytes_.data() + offset;
  }

  // Finds the end-of-central-directory record: the last place, within the 64 KiB comment
  // window at the end of the file, whose signature and comment length end exactly at EOF.
  EndRecord locate_end_record() const {
    const std::uint64_t size = bytes_.size();
    EPONA_CHECK(size >= kEndSize, name_, ": not a ZIP archive (", size, " bytes is too small)");
    const std::uint64_t lowest = size > kEndSize + kMaxComment ? size - kEndSize - kMaxComment : 0;
    for (std::uint64_t pos = size - kEndSize + 1; pos-- > lowest;) {
      const std::byte* p = bytes_.data() + pos;
      if (zip_detail::le32(p) != kEndSig || pos + kEndSize + zip_detail::le16(p + 20) != size) continue;
      return read_end_record(pos);
    }
    fail(name_, ": not a ZIP archive, or truncated: no end-of-central-directory record in its last ",
         size - lowest, " bytes");
  }

  EndRecord read_end_record(std::uint64_t pos) const {
    using namespace zip_detail;
    const std::byte* p = bytes_.data() + pos;
    const std::uint16_t disk = le16(p + 4), cd_disk = le16(p + 6), disk_entries = le16(p + 8),
                        entries = le16(p + 10);
    const std::uint32_t cd_size = le32(p + 12), cd_offset = le32(p + 16);
    EPONA_CHECK(disk == 0 && cd_disk == 0 && disk_entries == entries, name_,
                ": multi-disk (split) ZIP archives are not supported");
    EndRecord end{entries, cd_size, cd_offset, pos};
    const bool saturated = entries == 0xffff || cd_size == 0xffffffffu || cd_offset == 0xffffffffu;
    const bool has_locator = pos >= kZip64LocatorSize && le32(p - kZip64LocatorSize) == kZip64LocatorSig;
    if (has_locator) {
      end = read_zip64_end_record(pos - kZip64LocatorSize);
      check_agrees(entries, 0xffff, end.entries, "entry count");
      check_agrees(cd_size, 0xffffffffu, end.cd_size, "central directory size");
      check_agrees(cd_offset, 0xffffffffu, end.cd_offset, "central directory offset");
    } else {
      EPONA_CHECK(!saturated, name_,
                  ": the end record needs ZIP64 values, but there is no ZIP64 end-record locator");
    }
    EPONA_CHECK(end.cd_size <= end.cd_limit && end.cd_offset <= end.cd_limit - end.cd_size, name_,
                ": the central directory (", end.cd_size, " bytes at offset ", end.cd_offset,
                ") overlaps the end records at offset ", end.cd_limit, " (truncated or corrupt archive)");
    EPONA_CHECK(end.entries <= end.cd_size / kCentralSize, name_, ": the end record claims ", end.entries,
                " entries, but the central directory has only ", end.cd_size, " bytes");
    return end;
  }

  // A 16/32-bit end-record field must be saturated or equal to its ZIP64 counterpart.
  void check_agrees(std::uint64_t classic, std::uint64_t saturated, std::uint64_t zip64, const char* what) const {
    EPONA_CHECK(classic == saturated || classic == zip64, name_, ": the end record's ", what, " (", classic,
                ") disagrees with the ZIP64 end record (", zip64, ")");
  }

  EndRecord read_zip64_end_record(std::uint64_t locator_pos) const {
    using namespace zip_detail;
    const std::byte* loc = bytes_.data() + locator_pos;
    const std::uint32_t disk = le32(loc + 4), disks = le32(loc + 16);
    const std::uint64_t record_pos = le64(loc + 8);
    EPONA_CHECK(disk == 0 && disks <= 1, name_, ": multi-disk (split) ZIP64 archives are not supported");
    EPONA_CHECK(record_pos <= locator_pos && locator_pos - record_pos >= kZip64EndSize, name_,
                ": the ZIP64 end-record locator points to offset ", record_pos,
                ", which leaves no room for the record before the locator at ", locator_pos);
    const std::byte* r = bytes_.data() + record_pos;
    EPONA_CHECK(le32(r) == kZip64EndSig, name_, ": no ZIP64 end record at offset ", record_pos,
                " (corrupt archive)");
    const std::uint64_t record_size = le64(r + 4);
    EPONA_CHECK(record_size >= kZip64EndSize - 12 && record_size <= locator_pos - record_pos - 12, name_,
                ": the ZIP64 end record at offset ", record_pos, " has an invalid size ", record_size);
    EPONA_CHECK(le32(r + 16) == 0 && le32(r + 20) == 0 && le64(r + 24) == le64(r + 32), name_,
                ": multi-disk (split) ZIP64 archives are not supported");
    return EndRecord{le64(r + 32), le64(r + 40), le64(r + 48), record_pos};
  }

  // ZIP64 extended information (extra block 0x0001): one 64-bit value per saturated
  // header field, in the order uncompressed size, compressed size, local header offset.
  struct Zip64Fields {
    std::uint64_t* size = nullptr;
    std::uint64_t* compressed_size = nullptr;
    std::uint64_t* header_offset = nullptr;
  };
  void apply_zip64_extra(std::span<const std::byte> extra, Zip64Fields want, const std::string& entry,
                         const char* where) const {
    using namespace zip_detail;
    bool seen = false;
    std::size_t pos = 0;
    while (extra.size() - pos >= 4) {  // fewer than 4 trailing bytes: padding, ignored as zipfile does
      const std::uint16_t id = le16(extra.data() + pos), len = le16(extra.data() + pos + 2);
      pos += 4;
      EPONA_CHECK(len <= extra.size() - pos, name_, ": an extra field of entry '", entry, "' (", where,
                  ") runs past the end of its extra data");
      if (id == 0x0001) {
        EPONA_CHECK(!seen, name_, ": entry '", entry, "' has two ZIP64 extra fields (", where, ")");
        seen = true;
        std::size_t at = 0;
        for (std::uint64_t* field : {want.size, want.compressed_size, want.header_offset}) {
          if (!field) continue;
          EPONA_CHECK(len - at >= 8, name_, ": the ZIP64 extra field of entry '", entry, "' (", where,
                      ") is too short for its saturated sizes/offset");
          *field = le64(extra.data() + pos + at);
          at += 8;
        }
      }
      pos += len;
    }
    const bool needed = want.size || want.compressed_size || want.header_offset;
    EPONA_CHECK(seen || !needed, name_, ": entry '", entry, "' (", where,
                ") has saturated sizes/offset but no ZIP64 extra field");
  }

  void read_central_directory(const EndRecord& end) {
    using namespace zip_detail;
    entries_.reserve(static_cast<std::size_t>(end.entries));
    const std::uint64_t cd_end = end.cd_offset + end.cd_size;
    std::uint64_t pos = end.cd_offset;
    for (std::uint64_t i = 0; i < end.entries; ++i) {
      const std::string what = "central directory record " + std::to_string(i);
      EPONA_CHECK(cd_end - pos >= kCentralSize, name_, ": ", what, " runs past the end of the central directory");
      const std::byte* p = range(pos, kCentralSize, what);
      EPONA_CHECK(le32(p) == kCentralSig, name_, ": ", what, " at offset ", pos, " has a bad signature");
      const std::uint64_t name_len = le16(p + 28), extra_len = le16(p + 30), comment_len = le16(p + 32);
      const std::uint64_t record_len = kCentralSize + name_len + extra_len + comment_len;
      EPONA_CHECK(cd_end - pos >= record_len, name_, ": ", what, " runs past the end of the central directory");
      ZipEntry e;
      e.flags = le16(p + 8);
      e.method = le16(p + 10);
      e.crc32 = le32(p + 16);
      e.compressed_size = le32(p + 20);
      e.size = le32(p + 24);
      e.header_offset = le32(p + 42);
      e.name.assign(reinterpret_cast<const char*>(p + kCentralSize), name_len);
      check_name(e.name, what);
      const std::uint16_t disk = le16(p + 34);
      EPONA_CHECK(disk == 0 || disk == 0xffff, name_, ": entry '", e.name,
                  "' lies on another disk (split archive)");
      Zip64Fields z;
      if (e.size == 0xffffffffu) z.size = &e.size;
      if (e.compressed_size == 0xffffffffu) z.compressed_size = &e.compressed_size;
      if (e.header_offset == 0xffffffffu) z.header_offset = &e.header_offset;
      apply_zip64_extra({p + kCentralSize + name_len, extra_len}, z, e.name, "central directory");
      EPONA_CHECK(!(e.flags & kFlagEncrypted), name_, ": entry '", e.name, "' is encrypted");
      EPONA_CHECK(e.method != 0 || e.compressed_size == e.size, name_, ": stored entry '", e.name, "' has ",
                  e.compressed_size, " stored bytes but a size of ", e.size);
      EPONA_CHECK(index_.emplace(e.name, entries_.size()).second, name_, ": duplicate entry name '", e.name, "'");
      entries_.push_back(std::move(e));
      pos += record_len;
    }
    EPONA_CHECK(pos == cd_end, name_, ": the central directory has ", cd_end - pos,
                " bytes after its last record (entry count or size is wrong)");
  }

  void check_name(const std::string& n, const std::string& what) const {
    EPONA_CHECK(!n.empty(), name_, ": ", what, " has an empty name");
    EPONA_CHECK(n.find('\0') == std::string::npos, name_, ": ", what, " has a name with a NUL byte");
  }

  // The local header must repeat the central record (name, method, and sizes/CRC unless
  // they are deferred to a data descriptor); the data must end before the central directory.
  void check_local_header(ZipEntry& e, std::uint64_t cd_offset) {
    using namespace zip_detail;
    const std::string what = "local header of '" + e.name + "'";
    EPONA_CHECK(e.header_offset <= cd_offset && cd_offset - e.header_offset >= kLocalSize, name_, ": ", what,
                " (offset ", e.header_offset, ") is not before the central directory at ", cd_offset);
    const std::byte* p = range(e.header_offset, kLocalSize, what);
    EPONA_CHECK(le32(p) == kLocalSig, name_, ": ", what, " at offset ", e.header_offset, " has a bad signature");
    const std::uint16_t flags = le16(p + 6), method = le16(p + 8);
    const std::uint32_t crc = le32(p + 14);
    std::uint64_t csize = le32(p + 18), size = le32(p + 22);
    const std::uint64_t name_len = le16(p + 26), extra_len = le16(p + 28);
    const std::uint64_t header_len = kLocalSize + name_len + extra_len;
    EPONA_CHECK(cd_offset - e.header_offset >= header_len, name_, ": ", what, " runs into the central directory");
    EPONA_CHECK(std::string_view(reinterpret_cast<const char*>(p + kLocalSize), name_len) == e.name, name_, ": ",
                what, " names a different entry (central directory and local header disagree)");
    EPONA_CHECK(method == e.method && (flags & kFlagEncrypted) == 0, name_, ": ", what,
                " disagrees with the central directory on the compression method or encryption");
    Zip64Fields z;
    if (size == 0xffffffffu) z.size = &size;
    if (csize == 0xffffffffu) z.compressed_size = &csize;
    apply_zip64_extra({p + kLocalSize + name_len, extra_len}, z, e.name, "local header");
    // With a data descriptor (torch.save sets bit 3) the local CRC and sizes may be zero.
    const bool deferred = flags & kFlagDataDescriptor;
    auto agrees = [&](std::uint64_t local, std::uint64_t central) {
      return local == central || (deferred && local == 0);
    };
    EPONA_CHECK(agrees(crc, e.crc32) && agrees(csize, e.compressed_size) && agrees(size, e.size), name_, ": ",
                what, " disagrees with the central directory on the CRC or sizes (local: ", csize, "/", size,
                " bytes, central: ", e.compressed_size, "/", e.size, ")");
    e.data_offset = e.header_offset + header_len;
    EPONA_CHECK(e.compressed_size <= cd_offset - e.data_offset, name_, ": the data of entry '", e.name, "' (",
                e.compressed_size, " bytes at offset ", e.data_offset,
                ") runs into the central directory (truncated or corrupt archive)");
  }

  // Each entry (local header + data) must own its bytes: entries that overlap let one stretch of
  // the file be read under two names (or an entry hide inside another's data), which no writer
  // produces; a crafted archive used it to pass as well-formed.
  void check_no_overlap() const {
    std::vector<const ZipEntry*> order;
    for (const auto& e : entries_) order.push_back(&e);
    std::sort(order.begin(), order.end(),
              [](const ZipEntry* a, const ZipEntry* b) { return a->header_offset < b->header_offset; });
    for (std::size_t i = 1; i < order.size(); ++i) {
      const ZipEntry& prev = *order[i - 1];
      const ZipEntry& next = *order[i];
      const std::uint64_t prev_end = prev.data_offset + prev.compressed_size;
      EPONA_CHECK(next.header_offset >= prev_end, name_, ": entries '", printable(prev.name), "' (bytes ",
                  prev.header_offset, " to ", prev_end, ") and '", printable(next.name), "' (from byte ",
                  next.header_offset, ") overlap in the file (corrupt or crafted archive)");
    }
  }

  std::span<const std::byte> bytes_;
  std::shared_ptr<const void> owner_;
  std::string name_;
  std::vector<ZipEntry> entries_;
  std::unordered_map<std::string, std::size_t> index_;
};

}  // namespace epona::io
