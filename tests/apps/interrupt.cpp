// Issue #36, interrupts, with real signals: the `epona` program (fork + exec of the built binary;
// a signal needs a process of its own) is sent SIGINT in the middle of its work.
// - convert: the handler removes the "<out>.tmp-*" file being written; nothing else is left.
// - generate: the output folder says INCOMPLETE (written before the work, removed at the end).
// - generate --video (a program built with FFmpeg): the video's temporary file is removed too.
#include <doctest/doctest.h>

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "../temp_dir.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
using epona::test::read_file;

namespace {

#ifdef EPONA_CLI_PATH
// Starts the program with stdout/stderr into `log`; returns its pid.
pid_t spawn(const std::vector<std::string>& args, const fs::path& log) {
  const pid_t pid = ::fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) ::dup2(fd, 1), ::dup2(fd, 2);
    std::vector<char*> argv{const_cast<char*>("epona")};
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    ::execv(EPONA_CLI_PATH, argv.data());
    ::_exit(127);
  }
  return pid;
}

// Polls until `ready()` or the child exits or `seconds` pass; true when ready() held.
template <class F>
bool wait_for(pid_t pid, F&& ready, double seconds) {
  const auto end = Clock::now() + std::chrono::duration<double>(seconds);
  while (Clock::now() < end) {
    if (ready()) return true;
    int status = 0;
    if (::waitpid(pid, &status, WNOHANG) == pid) return ready();  // exited (reaped: status lost)
    std::this_thread::sleep_for(std::chrono::microseconds(200));
  }
  return ready();
}

int wait_status(pid_t pid) {
  int status = 0;
  ::waitpid(pid, &status, 0);
  return status;
}

std::vector<fs::path> temporaries(const fs::path& dir) {
  std::vector<fs::path> out;
  std::error_code ec;
  for (const auto& e : fs::recursive_directory_iterator(dir, ec))
    if (e.path().filename().string().find(".tmp-") != std::string::npos) out.push_back(e.path());
  return out;
}

// A safetensors file with one F32 tensor of `bytes` bytes, sparse (zeros cost no disk).
void sparse_safetensors(const fs::path& path, std::uint64_t bytes) {
  std::string header = "{\"w\":{\"dtype\":\"F32\",\"shape\":[" + std::to_string(bytes / 4) +
                       "],\"data_offsets\":[0," + std::to_string(bytes) + "]}}";
  header.resize((header.size() + 7) / 8 * 8, ' ');
  std::string head(8, '\0');
  for (int k = 0; k < 8; ++k) head[k] = static_cast<char>((std::uint64_t(header.size()) >> (8 * k)) & 0xff);
  head += header;
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  REQUIRE(fd >= 0);
  REQUIRE(::write(fd, head.data(), head.size()) == static_cast<ssize_t>(head.size()));
  REQUIRE(::ftruncate(fd, static_cast<off_t>(head.size() + bytes)) == 0);
  ::close(fd);
}
#endif

}  // namespace

#ifdef EPONA_CLI_PATH
TEST_CASE("SIGINT during convert removes the temporary output file") {
  epona::test::TempDir t("epona_interrupt");
  // Large enough that the write takes a while (hundreds of ms to seconds), sparse to read.
  sparse_safetensors(t.path / "in.safetensors", std::uint64_t{512} << 20);
  const fs::path out = t.path / "out" / "big.safetensors";
  fs::create_directories(out.parent_path());
  const pid_t pid = spawn({"convert", (t.path / "in.safetensors").string(), out.string(), "-q"}, t.path / "log");
  const bool writing = wait_for(pid, [&] { return !temporaries(out.parent_path()).empty(); }, 120);
  if (!writing) {
    const int status = wait_status(pid);
    FAIL("convert ended (status ", status, ") before its temporary file was seen: ", read_file(t.path / "log"));
  }
  ::kill(pid, SIGINT);
  const int status = wait_status(pid);
  CHECK(WIFSIGNALED(status));
  CHECK(WTERMSIG(status) == SIGINT);
  const auto left = temporaries(out.parent_path());
  CHECK_MESSAGE(left.empty(), "left: ", left.empty() ? std::string() : left.front().string());
  CHECK_FALSE(fs::exists(out));
  CHECK(read_file(t.path / "log").find("interrupted; removed the partial output files") != std::string::npos);
}

// (A finished run removes the note: tests/apps/cli.cpp, "generate 2 frames", in-process.)
TEST_CASE("SIGINT during generate leaves the folder marked INCOMPLETE") {
  epona::test::TempDir t("epona_interrupt");
  const fs::path dir = t.path / "gen";
  const pid_t pid = spawn({"generate", "-n", "50", "--steps", "1", "--out", dir.string(), "-q"}, t.path / "log");
  // The note is written before any work (the model is not even loaded yet when the signal comes).
  REQUIRE(wait_for(pid, [&] { return fs::exists(dir / "INCOMPLETE"); }, 120));
  ::kill(pid, SIGINT);
  const int status = wait_status(pid);
  CHECK(WIFSIGNALED(status));
  CHECK(fs::exists(dir / "INCOMPLETE"));
  CHECK(read_file(dir / "INCOMPLETE").find("incomplete") != std::string::npos);
  CHECK_FALSE(fs::exists(dir / "trajectory.json"));
  const auto left = temporaries(dir);
  CHECK_MESSAGE(left.empty(), "left: ", left.empty() ? std::string() : left.front().string());
}

#ifdef EPONA_CLI_HAS_FFMPEG
TEST_CASE("SIGINT during generate --video removes the video's temporary file") {
  epona::test::TempDir t("epona_interrupt");
  const fs::path dir = t.path / "gen", video = dir / "clip.mp4";
  const pid_t pid = spawn({"generate", "-n", "50", "--steps", "1", "--out", dir.string(), "--video", video.string(), "-q"},
                          t.path / "log");
  // The video's temporary file exists from before the first frame until the last.
  const auto writing_video = [&] {
    for (const auto& p : temporaries(dir))
      if (p.filename().string().rfind("clip.mp4.tmp-", 0) == 0) return true;
    return false;
  };
  if (!wait_for(pid, writing_video, 120)) {
    const int status = wait_status(pid);
    FAIL("generate ended (status ", status, ") before its video's temporary file was seen: ", read_file(t.path / "log"));
  }
  ::kill(pid, SIGINT);
  const int status = wait_status(pid);
  CHECK(WIFSIGNALED(status));
  const auto left = temporaries(dir);
  CHECK_MESSAGE(left.empty(), "left: ", left.empty() ? std::string() : left.front().string());
  CHECK_FALSE(fs::exists(video));
}
#endif
#else
TEST_CASE("interrupt tests need the epona program (EPONA_EXAMPLES)") { MESSAGE("skipped: no epona program built"); }
#endif
