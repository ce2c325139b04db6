// Issue #36 at the level of the `epona` program (in-process, apps/epona/cli.hpp): names with
// control bytes printed escaped, echoed input cut short, the resource limits and their options
// (--threads, --size, --max-pixels, --max-frames), output paths checked before the work, empty
// latents refused, and the one "epona: error:" line for filesystem and memory failures.
#include <doctest/doctest.h>

#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <new>
#include <sstream>
#include <string>
#include <vector>

#include "../../apps/epona/cli.hpp"
#include "../temp_dir.hpp"
#include "../io/zip_builder.hpp"
#include "cli_testing.hpp"
#include "epona/io/npy.hpp"
#include "epona/io/image.hpp"
#include "epona/io/safetensors.hpp"
#include "../golden_dir.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::check_cli_error;
using epona::test::write_file;
using epona::test::golden_dir;
using test::cli;
using test::has;

namespace {

std::vector<std::string> with_model(std::vector<std::string> args) {
  for (const auto& s : {"--weights", "", "--dcae", "", "--config", ""}) args.push_back(s);
  const auto n = args.size();
  args[n - 5] = golden_dir() + "/weights_world.safetensors";
  args[n - 3] = golden_dir() + "/weights_dcae.safetensors";
  args[n - 1] = golden_dir() + "/configs.json";
  return args;
}

// A torch.save-like .pkl whose `views` tensors all view one float storage of `numel` elements.
std::string shared_storage_pkl(int views, std::int64_t numel) {
  std::string p = "\x80\x02}(";
  const auto str = [&](const std::string& s) {
    p += 'X';
    zip_test::put<std::uint32_t>(p, static_cast<std::uint32_t>(s.size()));
    p += s;
  };
  const auto int32 = [&](std::int64_t v) {
    p += 'J';
    zip_test::put<std::int32_t>(p, static_cast<std::int32_t>(v));
  };
  for (int i = 0; i < views; ++i) {
    str("w" + std::to_string(i));
    p += "ctorch._utils\n_rebuild_tensor_v2\n((";
    str("storage");
    p += "ctorch\nFloatStorage\n";
    str("0");
    str("cpu");
    int32(numel);
    p += "tQ";
    int32(0);
    p += "(";
    int32(numel);
    p += "t(K\x01t\x89" "ccollections\nOrderedDict\n)RtR";
  }
  p += "u.";
  zip_test::ZipSpec z;
  z.entries.push_back({"arc/data.pkl", p});
  z.entries.push_back({"arc/data/0", std::string(std::size_t(numel) * 4, '\x01')});
  z.entries.push_back({"arc/version", "3\n"});
  return zip_test::layout_zip(z).bytes();
}

}  // namespace

TEST_CASE("convert refuses a .pkl whose views would repeat one storage many times over") {
  test::TempDir t;
  write_file(t.path / "views.pkl", shared_storage_pkl(40, 1 << 18));  // 1 MiB storage, 40 MiB of views
  const auto r = cli({"convert", t / "views.pkl", t / "out.safetensors", "-q"});
  check_cli_error(r, "distinct bytes of storage 40 times over");
  CHECK_FALSE(fs::exists(t.path / "out.safetensors"));
  write_file(t.path / "tied.pkl", shared_storage_pkl(2, 1 << 18));  // tied weights: written twice
  CHECK(cli({"convert", t / "tied.pkl", t / "tied.safetensors", "-q"}).rc == 0);
  CHECK(fs::file_size(t.path / "tied.safetensors") > 2u << 20);
}

TEST_CASE("info prints tensor names with ESC and NUL escaped") {
  test::TempDir t;
  Tensor<float> x({2});
  io::TensorMap m("mem");
  const std::string evil = std::string("module.\x1b[2J\x1b]0;owned\x07", 21) + std::string(1, '\0') + "x.weight";
  m.add(evil, io::raw_view(x));
  m.add("module.plain.weight", io::raw_view(x));
  const auto path = t / "evil.safetensors";
  io::save_safetensors(path, m, {{"note\x1b[31m", "red\x1b[0m"}});
  const auto r = cli({"info", path, "--keys"});
  CHECK(r.rc == 0);
  CHECK(r.out.find('\x1b') == std::string::npos);
  CHECK(r.out.find('\0') == std::string::npos);
  CHECK(r.out.find('\x07') == std::string::npos);
  CHECK_MESSAGE(has(r.out, "module.\\x1b[2J\\x1b]0;owned\\x07\\x00x.weight"), r.out);
  CHECK(has(r.out, "note\\x1b[31m = red\\x1b[0m"));
}

TEST_CASE("errors echo a short, escaped prefix of huge input") {
  test::TempDir t;
  const std::string huge(20 << 20, 'A');
  check_cli_error(cli({"encode", t / "x.png", "--size", huge, "-q"}), "--size must be HxW");
  // A 30 MB line of commas as actions: one short error, no 30M-field split.
  write_file(t.path / "commas.csv", std::string(30 << 20, ',') + "\n");
  check_cli_error(cli(with_model({"generate", "--trajectory", t / "commas.csv", "-q", "--out", t / "g"})),
              "expected 3 values (x, y, yaw), got more than 16: ',,,,");
  // Control bytes in an unknown option are escaped in the message.
  check_cli_error(cli({"info", "--\x1b[2Jevil"}), "\\x1b[2Jevil");
}

TEST_CASE("--threads, --size and --num-frames have upper bounds naming the option") {
  test::TempDir t;
  check_cli_error(cli({"encode", t / "x.png", "--threads", "100000", "-q"}), "--threads must be in [0, ");
  check_cli_error(cli({"encode", t / "x.png", "--size", "65536x65536", "-q"}), "longer than the limit of 16384");
  check_cli_error(cli({"encode", t / "x.png", "--size", "16384x16384", "-q"}), "(--max-pixels raises it)");
  check_cli_error(cli(with_model({"generate", "--num-frames", "20000", "-q", "--out", t / "g"})),
              "--num-frames 20000 is more than the limit of 10000 frames (--max-frames raises it)");
}

TEST_CASE("a trajectory of more actions than the frame limit is refused before any work") {
  test::TempDir t;
  std::string rows = "x,y,yaw\n";
  for (int i = 0; i < 10'001; ++i) rows += "1,0,0\n";
  write_file(t.path / "actions.csv", rows);
  const auto r = cli(with_model({"generate", "--trajectory", t / "actions.csv", "-q", "--out", t / "g"}));
  check_cli_error(r, "holds 10001 actions, more than the limit of 10000 frames");
  CHECK(has(r.err, "--max-frames"));
  CHECK_FALSE(fs::exists(t.path / "g"));  // refused before the output folder was made
}

TEST_CASE("encode refuses to encode beyond --max-pixels at the first image's size, before loading the model") {
  test::TempDir t;
  io::write_png(t / "a.png", io::Image(64, 64));
  check_cli_error(cli({"encode", t / "a.png", "--max-pixels", "2048", "-o", t / "z.npy", "-q"}),
              "encoding at its size 64x64 (4096 pixels) is more than the limit of 2048 (--max-pixels raises it");
  // The default is 16x the released 512x1024; a 16384-pixel --size side passes, 8.4M pixels do not.
  check_cli_error(cli({"encode", t / "a.png", "--size", "4096x4096", "-q", "-o", t / "z.npy"}),
              "more than the limit of 8388608 (--max-pixels raises it)");
}

TEST_CASE("decode refuses latents with no frames and grids beyond --max-pixels, before loading the model") {
  test::TempDir t;
  io::write_npy(t / "empty.npy", Tensor<float>({0, 32, 2, 4}));
  check_cli_error(cli({"decode", t / "empty.npy", "--out", t / "d", "-q"}), "hold no frames to decode");
  io::write_npy(t / "wide.npy", Tensor<float>({1, 1, 1, 2048}));
  check_cli_error(cli({"decode", t / "wide.npy", "--out", t / "d", "-q", "--max-pixels", "1048576"}),
              "more than the limit of 1048576 pixels (--max-pixels raises it)");
}

TEST_CASE("output paths: below a regular file, or in a read-only folder, refused before the work") {
  test::TempDir t;
  write_file(t.path / "file", "x");
  io::write_npy(t / "z.npy", Tensor<float>({1, 32, 1, 1}));
  check_cli_error(cli({"decode", t / "z.npy", "--out", (t.path / "file" / "sub").string(), "-q"}),
              "is a file, not a folder");
  check_cli_error(cli({"encode", t / "nothing.png", "-o", (t.path / "file" / "z.npy").string(), "-q"}),
              "is a file, not a folder");
  check_cli_error(cli({"convert", golden_dir() + "/weights_dcae.safetensors", (t.path / "file" / "o.safetensors").string()}),
              "is a file, not a folder");
  // /proc takes no new files, even from root: the probe finds it before any work.
  check_cli_error(cli({"decode", t / "z.npy", "--out", "/proc", "-q"}), "cannot write in the folder /proc");
  if (geteuid() != 0) {  // root writes anywhere else
    const fs::path ro = t.path / "ro";
    fs::create_directories(ro);
    ::chmod(ro.c_str(), 0555);
    check_cli_error(cli({"decode", t / "z.npy", "--out", ro.string(), "-q"}), "cannot write in the folder");
    check_cli_error(cli({"encode", t / "nothing.png", "-o", (ro / "z.npy").string(), "-q"}), "cannot write in the folder");
    ::chmod(ro.c_str(), 0755);
  }
}

TEST_CASE("filesystem errors and failed allocations become one line naming the activity") {
  app::current_activity() = "convert";
  {
    const app::Activity doing("writing out.safetensors");
    const std::filesystem::filesystem_error e("create_directories", fs::path("a/b"),
                                              std::make_error_code(std::errc::not_a_directory));
    CHECK(app::filesystem_text(e) == "convert: writing out.safetensors: Not a directory: 'a/b'");
  }
  CHECK(app::current_activity() == "convert");
  try {  // an exception leaving the stage keeps it for the handler, which runs after the unwinding
    const app::Activity doing("decoding 4 frame(s) of 512x1024");
    throw std::bad_alloc();
  } catch (const std::bad_alloc&) {
    CHECK(app::current_activity() == "convert: decoding 4 frame(s) of 512x1024");
  }
  std::ostringstream err;
  CHECK(app::fail_line(err, std::string("a\x1b[2Jb\nsecond line")) == 1);
  CHECK(err.str() == "epona: error: a\\x1b[2Jb\nsecond line\n");
}

// The one translation unit of this program that compiles stb.
#include "epona/io/stb_implementation.hpp"
