// Tests of include/epona/dist/ without MPI: the launch read from each launcher's variables (and
// refused when they are not numbers or not a rank of the size), the shares of the clips, the
// messages between ranks (exact round trip, a cut-short message refused), and the lone process.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "epona/dist/launch.hpp"
#include "epona/dist/message.hpp"
#include "epona/dist/process_group.hpp"

using namespace epona;

namespace {

const std::vector<const char*> kLauncherVariables = {
    "OMPI_COMM_WORLD_RANK", "OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_LOCAL_RANK", "OMPI_COMM_WORLD_LOCAL_SIZE",
    "PMI_RANK",             "PMI_SIZE",             "MPI_LOCALRANKID",            "MPI_LOCALNRANKS",
    "SLURM_PROCID",         "SLURM_STEP_NUM_TASKS", "SLURM_LOCALID",              "SLURM_NTASKS"};

// Sets the given variables for one case, with every launcher variable cleared first and restored after.
struct LauncherEnv {
  std::vector<std::pair<std::string, std::string>> saved;
  explicit LauncherEnv(const std::vector<std::pair<const char*, const char*>>& set) {
    for (const char* name : kLauncherVariables) {
      if (const char* v = std::getenv(name)) saved.emplace_back(name, v);
      ::unsetenv(name);
    }
    for (const auto& [name, value] : set) ::setenv(name, value, 1);
  }
  ~LauncherEnv() {
    for (const char* name : kLauncherVariables) ::unsetenv(name);
    for (const auto& [name, value] : saved) ::setenv(name.c_str(), value.c_str(), 1);
  }
};

void check_error(const std::function<void()>& f, const std::string& part) {
  try {
    f();
    FAIL("no error; expected one saying '", part, "'");
  } catch (const Error& e) {
    CHECK_MESSAGE(std::string(e.what()).find(part) != std::string::npos, e.what());
  }
}

}  // namespace

TEST_CASE("no launcher: one process") {
  LauncherEnv env({{"SLURM_PROCID", "0"}, {"SLURM_NTASKS", "4"}});  // a batch script's own shell
  const dist::Launch l = dist::launch_from_environment();
  CHECK(l.rank == 0);
  CHECK(l.size == 1);
  CHECK_FALSE(l.several());
  CHECK(l.launcher == "none");
}

TEST_CASE("each launcher's variables") {
  {
    LauncherEnv env({{"OMPI_COMM_WORLD_RANK", "3"}, {"OMPI_COMM_WORLD_SIZE", "4"}, {"OMPI_COMM_WORLD_LOCAL_RANK", "1"},
                     {"OMPI_COMM_WORLD_LOCAL_SIZE", "2"}});
    const dist::Launch l = dist::launch_from_environment();
    CHECK(l.launcher == "openmpi");
    CHECK((l.rank == 3 && l.size == 4 && l.local_rank == 1 && l.local_size == 2));
    CHECK(l.several());
  }
  {
    LauncherEnv env({{"PMI_RANK", "1"}, {"PMI_SIZE", "2"}});  // no local variables: the job is one host
    const dist::Launch l = dist::launch_from_environment();
    CHECK(l.launcher == "pmi");
    CHECK((l.rank == 1 && l.size == 2 && l.local_rank == 1 && l.local_size == 2));
  }
  {
    LauncherEnv env({{"SLURM_PROCID", "5"}, {"SLURM_STEP_NUM_TASKS", "8"}, {"SLURM_LOCALID", "1"}});
    const dist::Launch l = dist::launch_from_environment();
    CHECK(l.launcher == "slurm");
    CHECK((l.rank == 5 && l.size == 8 && l.local_rank == 1));
  }
}

TEST_CASE("launcher variables that are not a rank of the size are refused, naming the variable") {
  {
    LauncherEnv env({{"OMPI_COMM_WORLD_RANK", "0"}, {"OMPI_COMM_WORLD_SIZE", "two"}});
    check_error([] { dist::launch_from_environment(); }, "OMPI_COMM_WORLD_SIZE is not a process count or index: 'two'");
  }
  {
    LauncherEnv env({{"OMPI_COMM_WORLD_RANK", "2"}, {"OMPI_COMM_WORLD_SIZE", "2"}});
    check_error([] { dist::launch_from_environment(); }, "is not a rank of OMPI_COMM_WORLD_SIZE = 2");
  }
  {
    LauncherEnv env({{"PMI_SIZE", "2"}, {"MPI_LOCALRANKID", "0"}});  // no rank
    check_error([] { dist::launch_from_environment(); }, "PMI_RANK (-1) is not a rank");
  }
  {
    LauncherEnv env({{"PMI_RANK", "0"}, {"PMI_SIZE", "99999999999999999999"}});
    check_error([] { dist::launch_from_environment(); }, "PMI_SIZE is not a process count");
  }
  {
    LauncherEnv env({{"OMPI_COMM_WORLD_RANK", "0"}, {"OMPI_COMM_WORLD_SIZE", "2"}, {"OMPI_COMM_WORLD_LOCAL_RANK", "3"},
                     {"OMPI_COMM_WORLD_LOCAL_SIZE", "2"}});
    check_error([] { dist::launch_from_environment(); }, "OMPI_COMM_WORLD_LOCAL_RANK (3) is not below");
  }
}

TEST_CASE("the shares cover every item once, differing by at most one") {
  for (std::size_t count : {0, 1, 2, 7, 64})
    for (int size : {1, 2, 3, 5}) {
      std::vector<int> taken(count, 0);
      std::vector<std::size_t> per_rank;
      for (int rank = 0; rank < size; ++rank) {
        std::size_t n = 0;
        dist::for_each_share(count, rank, size, [&](std::size_t i) { ++taken[i], ++n; });
        CHECK(n == dist::share_size(count, rank, size));
        per_rank.push_back(n);
      }
      for (int t : taken) CHECK(t == 1);
      CHECK(*std::max_element(per_rank.begin(), per_rank.end()) - *std::min_element(per_rank.begin(), per_rank.end()) <= 1);
    }
}

TEST_CASE("a message reads back what was written, bit for bit") {
  dist::MessageWriter w;
  const std::vector<double> v = {0.1, -0.0, std::numeric_limits<double>::infinity(), 1e-310};
  w.put(std::uint8_t{7}).put(std::int64_t{-42}).put(std::string("clip_0001")).put(v).put(std::numeric_limits<double>::quiet_NaN());
  w.put(std::vector<float>{}).put(std::string());
  dist::MessageReader r(w.bytes());
  CHECK(r.get<std::uint8_t>() == 7);
  CHECK(r.get<std::int64_t>() == -42);
  CHECK(r.get_string() == "clip_0001");
  const auto back = r.get_vector<double>();
  REQUIRE(back.size() == v.size());
  for (std::size_t i = 0; i < v.size(); ++i) CHECK(std::memcmp(&back[i], &v[i], sizeof(double)) == 0);
  CHECK(std::isnan(r.get<double>()));
  CHECK(r.get_vector<float>().empty());
  CHECK(r.get_string().empty());
  CHECK(r.done());
}

TEST_CASE("a message cut short, or claiming more than it holds, is refused") {
  dist::MessageWriter w;
  w.put(std::string("abcdef")).put(std::vector<double>{1, 2, 3});
  const std::string whole = w.bytes();
  for (std::size_t n : {std::size_t{0}, std::size_t{3}, std::size_t{10}, whole.size() - 1}) {
    const std::string cut = whole.substr(0, n);
    check_error([&] {
      dist::MessageReader r(cut);
      r.get_string();
      r.get_vector<double>();
    }, "cut short");
  }
  dist::MessageWriter huge;
  huge.put(std::uint64_t{1} << 60);  // a length no message holds
  check_error([&] { dist::MessageReader(huge.bytes()).get_vector<double>(); }, "cut short");
  check_error([&] { dist::MessageReader(huge.bytes()).get_string(); }, "cut short");
}

TEST_CASE("a lone process's collectives are the identity") {
  dist::LoneProcess g;
  CHECK(g.rank() == 0);
  CHECK(g.size() == 1);
  CHECK(g.is_root());
  CHECK(g.gather_to_root("abc") == std::vector<std::string>{"abc"});
  CHECK(g.broadcast_from_root("xyz") == "xyz");
}
