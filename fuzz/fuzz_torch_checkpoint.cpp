// fuzz/fuzz_torch_checkpoint.cpp — load_torch_checkpoint (state dict selection, storage records,
// tensor views checked against records and declared sizes) on fuzzed content in a well-formed
// archive: the input is data.pkl, then each storage record, separated by kRecordSeparator; they
// are packed as torch.save does (archive/data.pkl, archive/data/<i>, archive/byteorder) with
// correct CRCs, so mutations reach the checkpoint logic instead of stopping at the ZIP checks
// (fuzz_zip covers those). Accepted tensors are converted to float.
#include "../tests/io/zip_builder.hpp"
#include "epona/io/torch_checkpoint.hpp"
#include "fuzz_common.hpp"

namespace torch_checkpoint_target {
constexpr std::string_view kRecordSeparator = "\xff\xfeREC";
}

EPONA_FUZZ_TARGET(torch_checkpoint) {
  using namespace torch_checkpoint_target;
  const auto parts = epona_fuzz::split(epona_fuzz::as_text(data, size), kRecordSeparator);
  zip_test::ZipSpec spec;
  spec.entries.push_back({"archive/data.pkl", std::string(parts[0])});
  spec.entries.push_back({"archive/byteorder", "little"});
  for (std::size_t i = 1; i < parts.size(); ++i)
    spec.entries.push_back({"archive/data/" + std::to_string(i - 1), std::string(parts[i]), ~0ull, 0, true});
  const std::string archive = zip_test::layout_zip(spec).bytes();
  return epona_fuzz::run([&] {
    const auto zip = zip_test::open_zip(archive, "fuzz.pkl");
    const auto map = epona::io::load_torch_checkpoint(zip, {.key = "", .verify_checksums = true});
    for (const auto& [name, raw] : map.entries())
      if (raw.dtype != epona::DType::I64) epona::io::to_tensor<float>(raw);
  });
}
