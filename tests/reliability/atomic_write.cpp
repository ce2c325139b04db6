// Tests that no writer of output files leaves a half-finished file: write_atomically
// (epona/io/atomic_file.hpp) interrupted by an exception from its fill function, and every writer
// of include/epona (save_safetensors, write_npy, write_trajectory as .csv/.json/.npy) interrupted
// by a failing write (a file-size limit, RLIMIT_FSIZE, makes write() fail with EFBIG part-way, as a
// full disk would), leave no file at a new destination, the old bytes at an existing one, and no
// temporary file behind. Concurrent writers of one path (threads of one process) leave one
// complete version.
#include <doctest/doctest.h>

#include <signal.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <fstream>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "epona/domain/trajectory_io.hpp"
#include "epona/io/atomic_file.hpp"
#include "epona/io/npy.hpp"
#include "epona/io/safetensors.hpp"
#include "../temp_dir.hpp"
#include "../files.hpp"

using namespace epona;
using epona::test::write_file;
using epona::test::read_file;
using epona::test::TempDir;
namespace fs = std::filesystem;

namespace {

// The names in a folder.
std::set<std::string> names_in(const fs::path& folder) {
  std::set<std::string> out;
  for (const auto& e : fs::directory_iterator(folder)) out.insert(e.path().filename().string());
  return out;
}

struct Interrupted {};  // thrown from inside a fill function

// Writes larger than this fail while the limit is in place (SIGXFSZ ignored, so write() returns
// EFBIG instead of killing the process). Restores the previous limit and handler on destruction.
class FileSizeLimit {
 public:
  explicit FileSizeLimit(rlim_t bytes) {
    REQUIRE(::getrlimit(RLIMIT_FSIZE, &old_) == 0);
    old_handler_ = ::signal(SIGXFSZ, SIG_IGN);
    rlimit lim = old_;
    lim.rlim_cur = bytes;
    REQUIRE(::setrlimit(RLIMIT_FSIZE, &lim) == 0);
  }
  ~FileSizeLimit() {
    ::setrlimit(RLIMIT_FSIZE, &old_);
    ::signal(SIGXFSZ, old_handler_);
  }

 private:
  rlimit old_{};
  void (*old_handler_)(int) = nullptr;
};

constexpr rlim_t kLimit = 4096;  // every output below is several times larger

Tensor<float> big_trajectory() {  // (S, W, 3) with S * W * 3 * 4 bytes well over kLimit
  Tensor<float> t({64, 15, 3});
  for (std::int64_t i = 0; i < t.numel(); ++i) t.data()[i] = 0.001f * static_cast<float>(i) - 1.5f;
  return t;
}

// Runs `write` (which must fail part-way) against a new and an existing destination.
template <class Write>
void check_interrupted_writer(const std::string& file_name, Write&& write) {
  TempDir dir;
  const fs::path dest = dir.path / file_name;
  {
    FileSizeLimit limit(kLimit);
    CHECK_THROWS_AS(write(dest), Error);
  }
  CHECK_MESSAGE(names_in(dir.path).empty(), "left behind: " << *names_in(dir.path).begin());

  write_file(dest, "the previous, complete output");
  {
    FileSizeLimit limit(kLimit);
    CHECK_THROWS_AS(write(dest), Error);
  }
  CHECK(read_file(dest) == "the previous, complete output");
  CHECK(names_in(dir.path) == std::set<std::string>{file_name});

  write(dest);  // without the limit the same writer succeeds, with the same single file
  CHECK(fs::file_size(dest) > kLimit);
  CHECK(names_in(dir.path) == std::set<std::string>{file_name});
}

}  // namespace

TEST_CASE("write_atomically writes the bytes, leaving only the destination") {
  TempDir dir;
  const fs::path dest = dir.path / "out.bin";
  std::string big(300000, '\0');  // larger than the sink's buffer: direct and buffered writes mixed
  for (std::size_t i = 0; i < big.size(); ++i) big[i] = static_cast<char>(i * 7 + 3);
  io::write_atomically(dest, [&](io::AtomicFileSink& out) {
    out.write("head", 4);
    out.write(big);
    out.write(std::string_view("tail"));
    CHECK(out.bytes_written() == 8 + big.size());
  });
  CHECK(read_file(dest) == "head" + big + "tail");
  io::write_atomically(dest, std::string_view("replaced"));
  CHECK(read_file(dest) == "replaced");
  io::write_atomically(dir.path / "empty", std::string_view());
  CHECK(fs::file_size(dir.path / "empty") == 0);
  CHECK(names_in(dir.path) == std::set<std::string>{"out.bin", "empty"});
}

TEST_CASE("an exception from the fill function leaves no file and no temporary file") {
  TempDir dir;
  const fs::path dest = dir.path / "out.bin";
  const std::string chunk(100000, 'x');  // part of it reaches the temporary file before the throw
  std::size_t files_before = 0;
  std::string old_content;
  auto interrupted = [&](io::AtomicFileSink& out) {
    out.write(chunk);
    out.write(chunk);
    CHECK(names_in(dir.path).size() == files_before + 1);  // the temporary file exists while writing ...
    CHECK((fs::exists(dest) ? read_file(dest) : "(none)") == old_content);  // ... the destination is untouched
    throw Interrupted{};
  };
  files_before = 0;
  old_content = "(none)";
  CHECK_THROWS_AS(io::write_atomically(dest, interrupted), Interrupted);
  CHECK(names_in(dir.path).empty());

  write_file(dest, "old");
  files_before = 1;
  old_content = "old";
  CHECK_THROWS_AS(io::write_atomically(dest, interrupted), Interrupted);
  CHECK(read_file(dest) == "old");
  CHECK(names_in(dir.path) == std::set<std::string>{"out.bin"});
}

TEST_CASE("write_atomically names the destination when it cannot write there") {
  TempDir dir;
  const fs::path missing = dir.path / "no-such-folder" / "out.bin";
  const std::string create_error = missing.string() + ": cannot create the temporary file";
  CHECK_THROWS_WITH_AS(io::write_atomically(missing, std::string_view("x")), doctest::Contains(create_error.c_str()),
                       Error);
  fs::create_directory(dir.path / "a-folder");
  CHECK_THROWS_WITH_AS(io::write_atomically(dir.path / "a-folder", std::string_view("x")),
                       doctest::Contains("is a directory"), Error);
  {
    const std::string write_error = (dir.path / "big").string() + ": write failed after";
    FileSizeLimit limit(kLimit);
    CHECK_THROWS_WITH_AS(io::write_atomically(dir.path / "big", std::string(3 * kLimit, 'y')),
                         doctest::Contains(write_error.c_str()), Error);
  }
  CHECK(names_in(dir.path) == std::set<std::string>{"a-folder"});
}

TEST_CASE("concurrent writers of one path leave one complete version") {
  TempDir dir;
  const fs::path dest = dir.path / "shared.bin";
  constexpr int kThreads = 4, kRounds = 8;
  constexpr std::size_t kBytes = 200000;
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t)
    threads.emplace_back([&, t] {
      const std::string bytes(kBytes, static_cast<char>('a' + t));
      for (int r = 0; r < kRounds; ++r) io::write_atomically(dest, std::string_view(bytes));
    });
  for (auto& th : threads) th.join();
  const std::string got = read_file(dest);
  REQUIRE(got.size() == kBytes);
  CHECK(std::count(got.begin(), got.end(), got[0]) == static_cast<std::ptrdiff_t>(kBytes));
  CHECK(names_in(dir.path) == std::set<std::string>{"shared.bin"});
}

// Threads of one process writing one path with a writer: the file left is one thread's complete output.
template <class Write, class Read>
void check_concurrent_writer(const std::string& file_name, Write&& write, Read&& read) {
  TempDir dir;
  const fs::path dest = dir.path / file_name;
  constexpr int kThreads = 4, kRounds = 6;
  std::vector<std::thread> threads;
  std::atomic<int> failures{0};  // a writer whose temporary file another thread took fails here
  for (int t = 0; t < kThreads; ++t)
    threads.emplace_back([&, t] {
      Tensor<float> values = Tensor<float>::full({64, 15, 3}, static_cast<float>(t + 1));
      for (int r = 0; r < kRounds; ++r) try {
          write(dest, values);
        } catch (const Error&) {
          ++failures;
        }
    });
  for (auto& th : threads) th.join();
  CHECK(failures == 0);
  const Tensor<float> got = read(dest);
  REQUIRE(got.numel() == 64 * 15 * 3);
  const float first = got.data()[0];
  CHECK((first >= 1 && first <= kThreads));
  CHECK(std::all_of(got.data(), got.data() + got.numel(), [&](float v) { return v == first; }));
  CHECK(names_in(dir.path) == std::set<std::string>{file_name});
}

TEST_CASE("concurrent writers through save_safetensors and write_npy leave one complete file") {
  check_concurrent_writer(
      "c.safetensors",
      [](const fs::path& p, const Tensor<float>& t) {
        io::TensorMap map;
        map.add("t", io::raw_view(t));
        io::save_safetensors(p.string(), map);
      },
      [](const fs::path& p) { return io::to_tensor<float>(io::read_safetensors(p.string()).tensors.at("t")); });
  check_concurrent_writer(
      "c.npy", [](const fs::path& p, const Tensor<float>& t) { io::write_npy(p, t); },
      [](const fs::path& p) { return io::read_npy<float>(p).values; });
}

TEST_CASE("every writer, interrupted part-way, leaves no partial output") {
  const Tensor<float> traj = big_trajectory();
  SUBCASE("save_safetensors") {
    check_interrupted_writer("w.safetensors", [&](const fs::path& p) {
      io::TensorMap map;
      map.add("traj", io::raw_view(traj));
      io::save_safetensors(p.string(), map, {{"note", "interrupted"}});
    });
  }
  SUBCASE("write_npy") {
    check_interrupted_writer("t.npy", [&](const fs::path& p) { io::write_npy(p, traj); });
  }
  SUBCASE("write_trajectory .csv") {
    check_interrupted_writer("t.csv", [&](const fs::path& p) { io::write_trajectory(p, traj); });
  }
  SUBCASE("write_trajectory .json") {
    check_interrupted_writer("t.json", [&](const fs::path& p) { io::write_trajectory(p, traj); });
  }
  SUBCASE("write_trajectory .npy") {
    check_interrupted_writer("t.npy", [&](const fs::path& p) { io::write_trajectory(p, traj); });
  }
}
