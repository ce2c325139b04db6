// fuzz/fuzz_safetensors.cpp — parse_safetensors on arbitrary bytes (the header JSON, offsets,
// shapes, dtypes, overlaps, __metadata__), then every accepted tensor converted to float.
#include "epona/io/safetensors.hpp"
#include "fuzz_common.hpp"

EPONA_FUZZ_TARGET(safetensors) {
  return epona_fuzz::run([&] {
    const auto file = epona::io::parse_safetensors(epona_fuzz::as_bytes(data, size), "fuzz.safetensors", nullptr);
    for (const auto& [name, raw] : file.tensors.entries()) {
      if (raw.dtype == epona::DType::I64) continue;  // refused by to_tensor<float>, tested elsewhere
      const auto t = epona::io::to_tensor<float>(raw);
      epona_fuzz::require(t.numel() == raw.numel(), "converted tensor has the raw tensor's size");
    }
  });
}
