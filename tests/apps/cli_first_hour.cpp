// The "first hour" slips of issue #37, each a test: what a new user met on the bundled model
// (models/small-synthetic) and the scripts, run in-process with captured stdout/stderr.
#include <doctest/doctest.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "../../apps/epona/cli.hpp"
#include "../../apps/epona/cmd_common.hpp"
#include "../../apps/epona/console.hpp"
#include "../temp_dir.hpp"
#include "cli_testing.hpp"
#include "epona/io/image.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::TempDir;
using test::cli;
using test::has;

namespace {

const std::string kModels = EPONA_MODELS_DIR;
const std::string kBundled = kModels + "/small-synthetic";
const std::string kFrame = kBundled + "/demo/frames/frame_00.png";

// stdout of a shell command (stderr joined), for the scripts.
std::string shell(const std::string& command) {
  std::string text;
  if (FILE* p = popen((command + " 2>&1").c_str(), "r")) {
    char buf[4096];
    for (std::size_t n; (n = std::fread(buf, 1, sizeof buf, p)) > 0;) text.append(buf, n);
    pclose(p);
  }
  return text;
}

void write_png_of(const fs::path& p, std::int64_t h, std::int64_t w) { io::write_png(p.string(), io::Image(h, w)); }

std::size_t lines(const std::string& s) { return static_cast<std::size_t>(std::count(s.begin(), s.end(), '\n')); }

}  // namespace

TEST_CASE("1. scripts/demo.sh --help prints its help text and nothing of its source") {
  const std::string help = shell("bash '" + kModels + "/../scripts/demo.sh' --help");
  CHECK(has(help, "Options of its own"));
  CHECK(has(help, "--no-cuda"));
  CHECK_FALSE(has(help, "set -euo"));
  CHECK_FALSE(has(help, "caller="));
  CHECK_FALSE(has(help, "root="));
}

TEST_CASE("4. info describes the bundled (smaller) model against the configs.json beside it") {
  const auto r = cli({"info", kBundled + "/weights_world.safetensors", kBundled + "/weights_dcae.safetensors"});
  REQUIRE(r.rc == 0);
  CHECK(has(r.err, "comparing with " + kBundled + "/configs.json"));
  CHECK(has(r.out, "matches " + kBundled + "/configs.json"));
  CHECK_FALSE(has(r.out, "not valid"));
  CHECK_FALSE(has(r.out, "does not fit"));
  CHECK_FALSE(has(r.out, "MISMATCH"));
}

TEST_CASE("5. info on a text file says it is not a checkpoint and what it looks like") {
  TempDir t;
  std::ofstream(t / "notes.txt") << "These are my notes about the model, not weights.\n";
  const auto r = cli({"info", t / "notes.txt"});
  CHECK(r.rc == 1);
  CHECK(has(r.err, "notes.txt: not a checkpoint"));
  CHECK(has(r.err, "safetensors"));
  CHECK(has(r.err, "text, starting \"These are my notes"));
  CHECK_FALSE(has(r.err, "header length"));
}

TEST_CASE("6. a size mismatch is told in the options' words, --size where it applies") {
  TempDir t;
  write_png_of(t.path / "a.png", 64, 64);
  write_png_of(t.path / "b.png", 32, 64);
  const auto first_sets = cli({"encode", t / "a.png", t / "b.png", "-o", t / "z.npy", "-q"});
  CHECK(first_sets.rc == 1);
  CHECK(has(first_sets.err, "--size HxW with --fit resize|crop|cover"));
  CHECK_FALSE(has(first_sets.err, "SizePolicy"));
  const auto sized = cli({"encode", t / "b.png", "--size", "64x64", "-o", t / "z.npy", "-q"});
  CHECK(sized.rc == 1);
  CHECK(has(sized.err, "--fit resize|crop|cover to convert it to --size"));
  CHECK_FALSE(has(sized.err, "SizePolicy"));
}

TEST_CASE("7. encode and decode --help name no --weights") {
  for (const char* command : {"encode", "decode"}) {
    const auto r = cli({command, "--help"});
    CHECK(r.rc == 0);
    CHECK(has(r.out, "--dcae"));
    CHECK_FALSE(has(r.out, "--weights"));
  }
}

TEST_CASE("8. notes agree in number and read as people write numbers") {
  CHECK(app::counted(1, "step") == "1 step");
  CHECK(app::counted(2, "step") == "2 steps");
  CHECK(app::grouped(769476) == "769,476");
  CHECK(app::grouped(999) == "999");
  CHECK(app::grouped(1000) == "1,000");
  CHECK(app::duration_text(0.00294264) == "2.9 ms");
  CHECK(app::duration_text(0.34) == "340 ms");
  CHECK(app::duration_text(1.44) == "1.4 s");
  CHECK(app::describe(DitSamplers::euler(1)) ==
        "planner euler x 1 step (1 DiT evaluation), video euler x 1 step (1 DiT evaluation)");
  TempDir t;
  const auto r = cli({"encode", kFrame, "-o", t / "z.npy", "--threads", "1"});
  REQUIRE(r.rc == 0);
  CHECK(has(r.err, " parameters in "));
  CHECK_FALSE(has(r.err, "e-0"));  // no 0.00294264 s or 2.9e-03 s
}

TEST_CASE("9 and 11. a model run names its backend, dtype and threads; --threads 0 means all") {
  TempDir t;
  const auto two = cli({"encode", kFrame, "-o", t / "z.npy", "--threads", "2"});
  REQUIRE(two.rc == 0);
  CHECK(two.err.rfind("epona: cpu, float32, 2 threads\n", 0) == 0);  // the first line
  const int hw = std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  const auto all = cli({"encode", kFrame, "-o", t / "z.npy", "--threads", "0", "--dtype", "bfloat16"});
  REQUIRE(all.rc == 0);
  CHECK(has(all.err, "epona: cpu, bfloat16, " + app::counted(hw, "thread") + "\n"));
  const auto quiet = cli({"encode", kFrame, "-o", t / "z.npy", "-q"});
  CHECK(quiet.rc == 0);
  CHECK_FALSE(has(quiet.err, "epona: cpu"));
  CHECK(has(cli({"encode", "--help"}).out, "0 or all: every hardware thread"));
}

TEST_CASE("10. a weight mismatch says what is wrong and what to do before a few example keys") {
  // The golden (conformance) DC-AE with the shipped configuration: hundreds of problems.
  const std::string golden = std::string(EPONA_GOLDEN_DEFAULT_DIR) + "/weights_dcae.safetensors";
  TempDir t;
  const auto r = cli({"encode", kFrame, "--dcae", golden, "-o", t / "z.npy", "-q"});
  REQUIRE(r.rc == 1);
  const auto differ = r.err.find("the checkpoint's shapes differ from the shipped Epona configuration in");
  const auto fix = r.err.find("to fix:");
  const auto keys = r.err.find("weight problem(s), e.g.");
  REQUIRE(differ != std::string::npos);
  REQUIRE(fix != std::string::npos);
  REQUIRE(keys != std::string::npos);
  CHECK(differ < fix);
  CHECK(fix < keys);
  CHECK(lines(r.err) <= 3);
  const std::string examples = r.err.substr(keys);
  CHECK(std::count(examples.begin(), examples.end(), ';') <= 3);  // three keys, then "..."
}

TEST_CASE("12. a run into an earlier run's folder leaves none of that run's files behind") {
  TempDir t;
  REQUIRE(cli({"encode", kFrame, "-o", t / "z.npy", "-q"}).rc == 0);
  {  // decode: frames beyond this run's count go
    fs::create_directories(t.path / "dec");
    write_png_of(t.path / "dec" / "frame_0005.png", 32, 32);
    write_png_of(t.path / "dec" / "keep_me.png", 32, 32);
    REQUIRE(cli({"decode", t / "z.npy", "-o", t / "dec", "-q"}).rc == 0);
    CHECK(fs::exists(t.path / "dec" / "frame_0000.png"));
    CHECK_FALSE(fs::exists(t.path / "dec" / "frame_0005.png"));
    CHECK(fs::exists(t.path / "dec" / "keep_me.png"));  // not a file epona writes
  }
  {  // generate: a latents.npy of an earlier --latents run, and its longer tail of frames
    const fs::path gen = t.path / "gen";
    fs::create_directories(gen / "frames");
    std::ofstream(gen / "latents.npy") << "stale";
    write_png_of(gen / "frames" / "frame_0003.png", 32, 32);
    const auto r = cli({"generate", "-n", "1", "--steps", "1", "-o", gen.string()});
    REQUIRE(r.rc == 0);
    CHECK(has(r.err, "generating 1 frame: "));  // 8.
    CHECK(has(r.out, "generated 1 frame of "));  // 8. (and its time in ms or s, not 0.1234567 s)
    CHECK_FALSE(has(r.out.substr(0, r.out.find('\n')), "e-0"));
    CHECK(fs::exists(gen / "frames" / "frame_0000.png"));
    CHECK_FALSE(fs::exists(gen / "frames" / "frame_0003.png"));
    CHECK_FALSE(fs::exists(gen / "latents.npy"));
  }
}

// The one translation unit of this program that compiles stb (after every other include).
#include "epona/io/stb_implementation.hpp"
