// Issue #40, data parallelism: the built `epona` program under `mpirun -np 2` (each rank takes
// every other clip, rank 0 gathers) writes the same eval report as one process, every metric and
// per-clip value equal, and `generate --clips` the same files; a clip failing on rank 1 fails the job with rank 1 and the file named and
// no report; commands that do not split their work refuse a launch of several processes. Runs
// the Release build's program (label mpi; .ci/run): the sanitized build compiles its programs at -O0.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "../temp_dir.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using epona::test::read_file;
using epona::test::read_json;

namespace {

#if defined(EPONA_CLI_PATH) && defined(EPONA_MPIEXEC)

// Runs a shell command line with its output into `log`; returns its exit status.
int run(const std::string& command, const fs::path& log) {
  const int status = std::system((command + " > '" + log.string() + "' 2>&1").c_str());
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128;
}

// The program's path quoted for the shell, then its arguments (appended, not concatenated with +:
// GCC 12 warns falsely on chains of std::string operator+ here, -Wrestrict).
std::string program(const std::string& args) {
  std::string command = "'";
  command.append(EPONA_CLI_PATH).append("' ").append(args);
  return command;
}

// mpirun of OpenMPI refuses root unless told (CI runs as root), and more ranks than cores unless told.
std::string mpirun(int ranks, const std::string& args) {
  ::setenv("OMPI_ALLOW_RUN_AS_ROOT", "1", 1);
  ::setenv("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1", 1);
  std::string command = "'";
  command.append(EPONA_MPIEXEC).append("' -np ").append(std::to_string(ranks)).append(" --oversubscribe ");
  return command.append(program(args));
}

// Three clips at the bundled model's size: two for rank 0, one for rank 1.
fs::path make_clips(const epona::test::TempDir& t) {
  const fs::path clips = t.path / "clips";
  REQUIRE(run(program("synth --clips 3 --frames 10 --future 2 --supersample 1 -q --out '" + clips.string() + "'"),
              t.path / "synth.log") == 0);
  return clips;
}

std::string eval_args(const fs::path& clips, const fs::path& report) {
  return "eval --clips '" + clips.string() + "' --json '" + report.string() +
         "' --steps 2 --horizon 2 --control --hypotheses 2 --threads 1 -q";
}

// The worst relative difference of two reports' numbers; the non-numbers must be equal.
double worst_difference(const json& a, const json& b) {
  if (a.is_number() && b.is_number()) {
    const double x = a.get<double>(), y = b.get<double>(), scale = std::max(std::abs(x), std::abs(y));
    return scale > 0 ? std::abs(x - y) / scale : 0.0;
  }
  if (a.type() != b.type() || a.size() != b.size()) return INFINITY;
  double worst = 0;
  if (a.is_object()) {
    for (const auto& [key, value] : a.items()) worst = std::max(worst, b.contains(key) ? worst_difference(value, b[key]) : INFINITY);
  } else if (a.is_array()) {
    for (std::size_t i = 0; i < a.size(); ++i) worst = std::max(worst, worst_difference(a[i], b[i]));
  } else if (a != b) {
    return INFINITY;
  }
  return worst;
}
#endif

}  // namespace

#if defined(EPONA_CLI_PATH) && defined(EPONA_MPIEXEC)
TEST_CASE("mpirun -np 2 epona eval gives the report of one process") {
  epona::test::TempDir t("epona_mpi");
  const fs::path clips = make_clips(t);
  const fs::path one = t.path / "one.json", two = t.path / "two.json";
  REQUIRE_MESSAGE(run(program(eval_args(clips, one)), t.path / "one.log") == 0, read_file(t.path / "one.log"));
  REQUIRE_MESSAGE(run(mpirun(2, eval_args(clips, two)), t.path / "two.log") == 0, read_file(t.path / "two.log"));
  json a = read_json(one), b = read_json(two);
  CHECK(a["settings"]["processes"] == 1);
  CHECK(b["settings"]["processes"] == 2);
  CHECK(b["clips"] == 3);
  REQUIRE(b["per_clip"].size() == 3);
  for (int i = 0; i < 3; ++i) CHECK(b["per_clip"][i]["name"] == "clip_000" + std::to_string(i));  // in clip order
  CHECK(b["model"]["psnr"].size() == 2);
  CHECK(b["model"]["l2_3s"].is_number());
  CHECK(b["control"]["scenes"] == 3);
  a["settings"].erase("processes"), b["settings"].erase("processes");
  CHECK_MESSAGE(a == b, "one process:\n", a.dump(1), "\ntwo processes:\n", b.dump(1));
}

// Issue #39: each rank batches its own clips (rank 0 runs clips 0 and 2 as one batch): the scores
// of one process with --batch 1, up to the rounding of the batched matrix products.
TEST_CASE("mpirun -np 2 epona eval --batch 2: each rank batches its own clips") {
  epona::test::TempDir t("epona_mpi");
  const fs::path clips = make_clips(t);
  const fs::path one = t.path / "one.json", two = t.path / "two.json";
  REQUIRE_MESSAGE(run(program(eval_args(clips, one)), t.path / "one.log") == 0, read_file(t.path / "one.log"));
  REQUIRE_MESSAGE(run(mpirun(2, eval_args(clips, two) + " --batch 2"), t.path / "two.log") == 0,
                  read_file(t.path / "two.log"));
  json a = read_json(one), b = read_json(two);
  CHECK(b["settings"]["batch"] == 2);
  CHECK(b["settings"]["processes"] == 2);
  for (json* r : {&a, &b}) (*r)["settings"].erase("processes"), (*r)["settings"].erase("batch");
  const double worst = worst_difference(a, b);
  MESSAGE("mpirun -np 2 --batch 2 vs one process --batch 1: worst relative difference ", worst);
  CHECK(worst <= 1e-4);
}

TEST_CASE("mpirun -np 2 epona generate --clips writes the files of one process") {
  epona::test::TempDir t("epona_mpi");
  const fs::path clips = make_clips(t);
  const auto args = [&](const fs::path& out) {
    return "generate --clips '" + clips.string() + "' -n 2 --steps 2 --threads 1 -q --out '" + out.string() + "'";
  };
  REQUIRE_MESSAGE(run(program(args(t.path / "one")), t.path / "one.log") == 0, read_file(t.path / "one.log"));
  REQUIRE_MESSAGE(run(mpirun(2, args(t.path / "two")), t.path / "two.log") == 0, read_file(t.path / "two.log"));
  for (const char* clip : {"clip_0000", "clip_0001", "clip_0002"})
    for (const char* file : {"trajectory.json", "poses.csv", "contact_sheet.png", "frames/frame_0000.png", "frames/frame_0001.png"}) {
      const fs::path a = t.path / "one" / clip / file, b = t.path / "two" / clip / file;
      REQUIRE_MESSAGE(fs::exists(b), b.string());
      CHECK_MESSAGE(read_file(a) == read_file(b), b.string());
      CHECK_FALSE(fs::exists(t.path / "two" / clip / "INCOMPLETE"));
    }
  const std::string log = read_file(t.path / "two.log");
  CHECK_MESSAGE(log.find("generated 2 frames for each of 3 clips") != std::string::npos, log);
}

TEST_CASE("a clip failing on rank 1 fails the job, naming the rank and the file; no report") {
  epona::test::TempDir t("epona_mpi");
  const fs::path clips = make_clips(t);
  const fs::path bad = clips / "clip_0001" / "future" / "frame_00.png";  // clip 1 is rank 1's
  REQUIRE(fs::exists(bad));
  std::ofstream(bad) << "not an image";
  const fs::path report = t.path / "r.json";
  CHECK(run(mpirun(2, eval_args(clips, report)), t.path / "log") != 0);
  const std::string log = read_file(t.path / "log");
  CHECK_MESSAGE(log.find("process 1 of 2: ") != std::string::npos, log);
  CHECK_MESSAGE(log.find("clip_0001/future/frame_00.png: not a PNG or JPEG file") != std::string::npos, log);
  CHECK_FALSE(fs::exists(report));
}

TEST_CASE("a command that does not split its work refuses several processes") {
  epona::test::TempDir t("epona_mpi");
  CHECK(run(mpirun(2, "plan -q --out '" + (t.path / "plan").string() + "'"), t.path / "log") != 0);
  const std::string log = read_file(t.path / "log");
  CHECK_MESSAGE(log.find("plan runs as one process, but openmpi started 2") != std::string::npos, log);
  CHECK_FALSE(fs::exists(t.path / "plan" / "trajectory.json"));
}
#else
TEST_CASE("mpirun tests skipped") {
  MESSAGE("skipped: this build has no MPI (EPONA_MPI) or no epona program (EPONA_EXAMPLES)");
}
#endif
