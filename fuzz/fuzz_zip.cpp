// fuzz/fuzz_zip.cpp — the ZIP reader (end record search, ZIP64 records and extra fields, central
// directory, local headers, data bounds) on arbitrary bytes; every stored entry's CRC is checked,
// which reads all of its bytes through the returned view.
#include "epona/io/zip.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(zip) {
  return epona_fuzz::run([&] {
    const epona::io::ZipArchive zip(epona_fuzz::as_bytes(data, size), nullptr, "fuzz.zip");
    for (const auto& e : zip.entries()) {
      epona_fuzz::require(zip.find(e.name) == &e, "every entry is found by its name");
      if (e.method == 0) zip.verify_crc(e);
    }
  });
}
