// fuzz/fuzz_poses_npy.cpp — load_poses and read_actions on a fuzzed pose.npy (absolute poses
// (N, 4, 4) / (1, N, 4, 4) through get_rel_pose, (N, 3) rows, planned (S, W, 3) trajectories) and,
// when the input holds kYawSeparator, a fuzzed yaw.npy beside it (the official demo's pair).
// These readers take paths only, so each input is written to a tmpfs folder (/dev/shm).
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "epona/domain/trajectory_io.hpp"
#include "fuzz_common.hpp"

namespace poses_npy_target {
namespace fs = std::filesystem;
constexpr std::string_view kYawSeparator = "\xff\xfeYAW";

const fs::path& work_dir() {
  static const fs::path dir = [] {
    const fs::path d = fs::path(fs::exists("/dev/shm") ? "/dev/shm" : fs::temp_directory_path()) /
                       ("epona-fuzz-poses-" + std::to_string(::getpid()));
    fs::create_directories(d);
    std::atexit([] { std::error_code ec; fs::remove_all(work_dir(), ec); });
    return d;
  }();
  return dir;
}

void put(const fs::path& path, std::string_view bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!out) epona_fuzz::bug("cannot write the fuzz input to", path.c_str());
}
}  // namespace poses_npy_target

EPONA_FUZZ_TARGET(poses_npy) {
  using namespace poses_npy_target;
  const auto parts = epona_fuzz::split(epona_fuzz::as_text(data, size), kYawSeparator);
  const fs::path pose = work_dir() / "pose.npy", yaw = work_dir() / "yaw.npy";
  put(pose, parts[0]);
  std::error_code ec;
  if (parts.size() > 1) put(yaw, parts[1]);
  else fs::remove(yaw, ec);
  epona_fuzz::run([&] { epona::io::load_poses(pose); });
  return epona_fuzz::run([&] { epona::io::read_actions(pose); });
}
