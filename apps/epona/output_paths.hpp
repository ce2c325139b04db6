// apps/epona/output_paths.hpp — output folders and files checked before the work starts: created
// if missing, refused with a clear message when a part of the path is a file, and probed for
// writing, so a read-only folder is found in a second rather than after an hour of rollout.
#pragma once

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <string>
#include <system_error>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/io/atomic_file.hpp"

namespace epona::app {

namespace output_detail {

// The first part of `p` (from the root down) that exists and is not a folder, or empty.
inline std::filesystem::path file_in_the_way(const std::filesystem::path& p) {
  std::filesystem::path partial;
  for (const auto& part : p) {
    partial /= part;
    std::error_code ec;
    const auto st = std::filesystem::status(partial, ec);
    if (ec || !std::filesystem::exists(st)) return {};  // the rest will be created
    if (!std::filesystem::is_directory(st)) return partial;
  }
  return {};
}

// Creates and removes a probe file: the one check that covers permissions, read-only mounts and
// ACLs alike (access(2) does not see all of them).
inline void check_writable(const std::filesystem::path& dir, const std::string& what) {
  const auto probe = dir / (".epona-write-test-" + std::to_string(getpid()));
  const int fd = ::open(probe.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
  if (fd < 0) {
    const int err = errno;
    if (err == EEXIST) return;  // another epona of this pid's number: the folder takes files
    fail(what, ": cannot write in the folder ", dir.string(), " (", std::strerror(err), ")");
  }
  ::close(fd);
  ::unlink(probe.c_str());
}

}  // namespace output_detail

// Makes `dir` (and its parents) a writable folder, or throws naming `what` ("--out out/plan").
inline void prepare_output_dir(const std::filesystem::path& dir, const std::string& what) {
  const auto blocker = output_detail::file_in_the_way(dir);
  EPONA_CHECK(blocker.empty(), what, ": ", blocker.string(), " is a file, not a folder, so ", dir.string(),
              " cannot be created below it");
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  EPONA_CHECK(std::filesystem::is_directory(dir, ec), what, ": cannot create the output folder ", dir.string(),
              ec ? " (" + ec.message() + ")" : std::string());
  output_detail::check_writable(dir, what);
}

// The folder of an output file made ready as above; a folder at `file` itself is refused.
inline void prepare_output_file(const std::filesystem::path& file, const std::string& what) {
  std::error_code ec;
  EPONA_CHECK(!std::filesystem::is_directory(file, ec), what, ": ", file.string(), " is a folder, not a file name");
  const auto parent = file.parent_path();
  prepare_output_dir(parent.empty() ? std::filesystem::path(".") : parent, what);
}

// Outputs of an earlier run into the same folder that this run will not write: a stale
// latents.npy or frame_0059.png beside this run's files would pass for this run's (issue #37).
// Removed before the work starts, so an interrupted run does not leave a mix either.
inline void remove_stale_output(const std::filesystem::path& file) {
  std::error_code ec;
  if (std::filesystem::is_regular_file(file, ec)) std::filesystem::remove(file, ec);
}

// frame_NNNN.png files of `dir` numbered `first` and up (a longer earlier run's tail).
inline void remove_stale_frames(const std::filesystem::path& dir, std::int64_t first) {
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) return;
  std::vector<std::filesystem::path> stale;
  for (const auto& e : std::filesystem::directory_iterator(dir, ec)) {
    const std::string name = e.path().filename().string();
    if (name.size() < 14 || name.rfind("frame_", 0) != 0 || e.path().extension() != ".png") continue;
    const std::string digits = name.substr(6, name.size() - 10);
    if (digits.empty() || digits.size() > 9 || digits.find_first_not_of("0123456789") != std::string::npos) continue;
    if (std::stoll(digits) >= first) stale.push_back(e.path());
  }
  for (const auto& p : stale) remove_stale_output(p);
}

// An INCOMPLETE note in an output folder while a long run fills it: written before the first
// output, removed by done() after the last. An interrupt, a crash or an error leaves it there,
// so a folder of frames without trajectory or poses files says what it is. No handler needed.
class IncompleteMarker {
 public:
  IncompleteMarker(const std::filesystem::path& dir, const std::string& what) : path_(dir / "INCOMPLETE") {
    io::write_atomically(path_, what + ": started; this folder is incomplete until the run ends, which removes "
                                       "this file (an interrupt, crash or error leaves it)\n");
  }
  IncompleteMarker(const IncompleteMarker&) = delete;
  IncompleteMarker& operator=(const IncompleteMarker&) = delete;
  void done() {
    std::error_code ec;
    std::filesystem::remove(path_, ec);
  }

 private:
  std::filesystem::path path_;
};

}  // namespace epona::app
