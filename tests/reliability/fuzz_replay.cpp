// Replays every fuzz target (fuzz/fuzz_<target>.cpp, compiled here without libFuzzer) over its
// seed corpus fuzz/corpus/<target>/ and every input a fuzzer ever found a bug with,
// fuzz/regressions/<target>/. A target aborts on anything but a result or an epona::Error, and the
// sanitizer build (scripts/test-sanitize.sh) adds ASan/UBSan/LSan, so each past crash, leak or UB
// stays a failing test if it comes back.
#include <doctest/doctest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#define EPONA_FUZZ_REPLAY
#include "../../fuzz/fuzz_config_json.cpp"
#include "../../fuzz/fuzz_image.cpp"
#include "../../fuzz/fuzz_npy.cpp"
#include "../../fuzz/fuzz_pickle.cpp"
#include "../../fuzz/fuzz_poses_csv.cpp"
#include "../../fuzz/fuzz_poses_json.cpp"
#include "../../fuzz/fuzz_poses_npy.cpp"
#include "../../fuzz/fuzz_safetensors.cpp"
#include "../../fuzz/fuzz_torch_checkpoint.cpp"
#include "../../fuzz/fuzz_trajectory_csv.cpp"
#include "../../fuzz/fuzz_trajectory_json.cpp"
#include "../../fuzz/fuzz_zip.cpp"

namespace fs = std::filesystem;

namespace {

const fs::path kFuzzDir = fs::path(EPONA_TEST_DATA_DIR) / ".." / ".." / "fuzz";

// Runs `target` on every file of fuzz/corpus/<name>/ and fuzz/regressions/<name>/; returns how many.
template <class Target>
std::size_t replay(const std::string& name, Target target) {
  std::size_t n = 0;
  for (const char* set : {"corpus", "regressions"}) {
    const fs::path dir = kFuzzDir / set / name;
    if (!fs::is_directory(dir)) continue;
    for (const auto& entry : fs::directory_iterator(dir)) {
      std::ifstream in(entry.path(), std::ios::binary);
      const std::string bytes{std::istreambuf_iterator<char>(in), {}};
      INFO("input ", entry.path().string());
      CHECK(target(reinterpret_cast<const std::uint8_t*>(bytes.data()), bytes.size()) == 0);
      ++n;
    }
  }
  return n;
}

}  // namespace

#define REPLAY(target) \
  TEST_CASE("fuzz target " #target " on its seeds and past findings") { CHECK(replay(#target, fuzz_##target) > 0); }

REPLAY(config_json)
REPLAY(image)
REPLAY(npy)
REPLAY(pickle)
REPLAY(poses_csv)
REPLAY(poses_json)
REPLAY(poses_npy)
REPLAY(safetensors)
REPLAY(torch_checkpoint)
REPLAY(trajectory_csv)
REPLAY(trajectory_json)
REPLAY(zip)
