// Tests of the `epona` command-line program (apps/epona/cli.hpp), run in-process with captured
// stdout/stderr: usage errors (exit 1, "epona: error: ..."), --help of every command, `info` on
// the golden checkpoints (.safetensors and .pkl; --write-config round trip), encode/decode and
// plan/generate against the library called directly (bit-equal), PNG sizes read back with stb,
// determinism (two runs, identical bytes), replay of a logged trajectory, and bad inputs.
// Model: the golden set (EPONA_GOLDEN_DIR); the bundled-demo tests use tests/data as built in.
#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <unistd.h>

#include "../../apps/epona/cli.hpp"
#include "../../apps/epona/console.hpp"
#include "../../apps/epona/drawing.hpp"
#include "../../apps/epona/frames.hpp"
#include "../../apps/epona/video_output.hpp"
#include "../temp_dir.hpp"
#include "cli_testing.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "epona/domain/config_json.hpp"
#include "epona/io/image.hpp"
#include "epona/io/npy.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/model/dcae.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/rollout.hpp"
#include "../golden_dir.hpp"
#include "../files.hpp"

namespace fs = std::filesystem;
using namespace epona;
using epona::test::check_cli_error;
using epona::test::write_file;
using epona::test::read_file;
using epona::test::TempDir;
using epona::test::golden_dir;

namespace {

using test::cli;
using test::has;
using Result = test::CliResult;

const io::ModelConfigs& golden_configs() {
  static const io::ModelConfigs c = io::load_configs(golden_dir() + "/configs.json");
  return c;
}
std::vector<std::string> golden_model_args() {
  return {"--weights", golden_dir() + "/weights_world.safetensors", "--dcae", golden_dir() + "/weights_dcae.safetensors",
          "--config", golden_dir() + "/configs.json"};
}

io::Image demo_frame(int i) {
  return io::read_image(std::string(EPONA_TEST_DATA_DIR) + "/demo/frame_0" + std::to_string(i) + ".png");
}

// `count` frames at the golden world model's size (the demo frames, resized and repeated) and a
// poses.csv with `pose_rows` rows (2 m forward each, optionally one row spoiled).
fs::path make_clip(const TempDir& t, std::int64_t count, std::int64_t pose_rows, const std::string& bad_row = "") {
  const auto& w = golden_configs().world;
  const fs::path dir = t.path / "clip";
  fs::create_directories(dir);
  for (std::int64_t i = 0; i < count; ++i)
    io::write_png((dir / ("f" + std::to_string(i) + ".png")).string(),
                  io::resize_bicubic(demo_frame(static_cast<int>(i % 3)), w.image_h, w.image_w));
  std::string csv = "x,y,yaw\n";
  for (std::int64_t i = 0; i < pose_rows; ++i) csv += (i == 1 && !bad_row.empty()) ? bad_row + "\n" : "2.0,0.1,0.5\n";
  write_file(dir / "poses.csv", csv);
  return dir;
}

// Decodes a PNG with stb and checks it is 8-bit RGB of h x w.
void check_png(const std::string& path, std::int64_t h, std::int64_t w) {
  INFO(path);
  REQUIRE(fs::exists(path));
  int width = 0, height = 0, channels = 0;
  unsigned char* pixels = stbi_load(path.c_str(), &width, &height, &channels, 0);
  REQUIRE(pixels != nullptr);
  stbi_image_free(pixels);
  CHECK(height == h);
  CHECK(width == w);
  CHECK(channels == 3);
}

// The library called directly on a clip folder: the window the CLI must build.
template <class Dc>
History history_of(cpu::Context& ctx, const Dc& dcae, const fs::path& clip, const io::PoseSequence& poses) {
  const auto files = app::list_images(clip, "test");
  std::vector<io::Image> frames;
  const std::int64_t F = golden_configs().world.condition_frames;
  for (std::size_t i = files.size() - static_cast<std::size_t>(F); i < files.size(); ++i)
    frames.push_back(io::read_image(files[i].string()));
  const Tensor<float> z = dcae.encode(ctx, io::images_to_tensor(frames));  // (F, C, h, w)
  const Tensor<float> tokens = latent_to_tokens(ctx, z);
  io::PoseSequence last;
  for (std::size_t i = poses.size() - static_cast<std::size_t>(F); i < poses.size(); ++i)
    last.x.push_back(poses.x[i]), last.y.push_back(poses.y[i]), last.yaw.push_back(poses.yaw[i]);
  // The window's first frame has no motion, as get_rel_pose of the window's own poses gives it
  // in the official training and test_traj.py.
  last.x[0] = last.y[0] = last.yaw[0] = 0.0f;
  return {tokens.reshape({1, F, tokens.size(1), tokens.size(2)}), last.pose_tensor(), last.yaw_tensor()};
}

// generate of 2 frames of `clip` (its frames and poses.csv) on the golden model: 2 steps, seed 3,
// the latents kept; --out not yet given.
std::vector<std::string> two_frames_of(const fs::path& clip) {
  std::vector<std::string> args = {"generate", "-n", "2", "--steps", "2", "--seed", "3", "--latents", "--frames",
                                   clip.string(), "--poses", (clip / "poses.csv").string()};
  for (const auto& a : golden_model_args()) args.push_back(a);
  return args;
}

void check_same(const Tensor<float>& a, const Tensor<float>& b) {
  REQUIRE(a.shape() == b.shape());
  std::int64_t differ = 0;
  for (std::int64_t i = 0; i < a.numel(); ++i) differ += a.data()[i] != b.data()[i];
  CHECK(differ == 0);
}

}  // namespace

TEST_CASE("usage errors exit 1 with 'epona: error:' and name the problem") {
  check_cli_error(cli({}), "no command given");
  check_cli_error(cli({"fly"}), "unknown command 'fly'");
  check_cli_error(cli({"plan", "--bogus"}), "unknown option '--bogus'");
  check_cli_error(cli({"plan", "-z"}), "unknown option '-z'");
  check_cli_error(cli({"plan", "--steps"}), "--steps needs a value");
  check_cli_error(cli({"plan", "--steps", "0"}), "--steps must be in [1, 100000], got 0");
  check_cli_error(cli({"plan", "--steps", "ten"}), "--steps needs an integer, got 'ten'");
  check_cli_error(cli({"plan", "--steps=3x"}), "--steps needs an integer");
  check_cli_error(cli({"plan", "--seed", "-1"}), "--seed must be at least 0, got -1");
  check_cli_error(cli({"plan", "--solver", "rk4"}), "--solver: unknown solver 'rk4' (one of euler, heun, midpoint, dpmpp2m)");
  check_cli_error(cli({"plan", "--sampler", "turbo"}), "--sampler must be one of official, fast; got 'turbo'");
  check_cli_error(cli({"plan", "--plan-steps", "0"}), "--plan-steps must be in [1, 100000], got 0");
  check_cli_error(cli({"generate", "--video-steps", "100001"}), "--video-steps must be in [1, 100000], got 100001");
  check_cli_error(cli({"eval", "--clips", ".", "--json", "r.json", "--solver", "Euler"}), "unknown solver 'Euler'");
  check_cli_error(cli({"plan", "--seed", "1", "--seed", "2"}), "--seed given more than once");
  check_cli_error(cli({"plan", "--quiet=yes"}), "--quiet takes no value");
  check_cli_error(cli({"plan", "extra"}), "unexpected argument 'extra'");
  check_cli_error(cli({"plan", "--backend", "tpu"}), "--backend must be one of cpu, cuda; got 'tpu'");
  check_cli_error(cli({"plan", "--dtype", "int8"}), "--dtype must be one of");
  check_cli_error(cli({"generate", "-n", "0"}), "--num-frames must be at least 1, got 0");
  check_cli_error(cli({"generate", "--decode", "gif"}), "--decode must be one of clip, frame");
  check_cli_error(cli({"decode", "z.npy", "--video"}), "--video needs a value (FILE)");
  check_cli_error(cli({"info"}), "missing checkpoint file(s)");
  check_cli_error(cli({"decode"}), "missing latents file");
  check_cli_error(cli({"encode", "x.png", "--size", "100x200"}), "--size must be HxW with positive multiples of 32");
  check_cli_error(cli({"plan", "--dcae", golden_dir() + "/weights_dcae.safetensors"}), "--weights FILE");
}

TEST_CASE("progress: rate, elapsed and time left; in place on a terminal, a line per tenth otherwise") {
  CHECK(app::clock_text(7.4) == "00:07");
  CHECK(app::clock_text(723) == "12:03");
  CHECK(app::clock_text(3725) == "1:02:05");
  CHECK(app::rate_text(3, 1.5, "frame") == "2.00 frame/s");
  CHECK(app::rate_text(1, 4, "frame") == "4.00 s/frame");
  std::ostringstream out, log, tty;
  {
    const app::Console con{out, log, false, false};
    app::Progress bar(con, "work", 20, "item");
    for (int i = 0; i < 20; ++i) bar.advance();
  }
  // Non-interactive: one line per tenth (20 items -> 10 lines), the last without "left".
  const std::string lines = log.str();
  CHECK(std::count(lines.begin(), lines.end(), '\n') == 10);
  CHECK(has(lines, "work [############------------] 10/20 items"));
  CHECK(has(lines, "left "));
  CHECK(has(lines, "work [########################] 20/20 items"));
  {
    const app::Console con{out, tty, false, true};
    app::Progress bar(con, "work", 4, "item");
    for (int i = 0; i < 4; ++i) bar.advance();
  }
  CHECK(has(tty.str(), "\r"));
  CHECK(has(tty.str(), "\x1b[K"));
  CHECK(tty.str().back() == '\n');
  std::ostringstream silent;
  {
    const app::Console con{out, silent, true, true};
    app::Progress bar(con, "work", 4, "item");
    bar.advance(4);
    con.note("a note");
  }
  CHECK(silent.str().empty());
  CHECK(out.str().empty());
}

TEST_CASE("frames are listed in natural name order") {
  CHECK(app::natural_less("f2.png", "f10.png"));
  CHECK_FALSE(app::natural_less("f10.png", "f2.png"));
  CHECK(app::natural_less("frame_002.png", "frame_10.png"));
  CHECK(app::natural_less("a.png", "b.png"));
  CHECK_FALSE(app::natural_less("a.png", "a.png"));
}

TEST_CASE("--backend cuda is refused with a reason, never a crash") {
  const Result r = cli({"plan", "--backend", "cuda"});
#if defined(EPONA_WITH_CUDA)
  check_cli_error(r, "this program was built without its CUDA engine");  // the epona binary has it; this test does not
#else
  check_cli_error(r, "this build has no CUDA backend");
#endif
}

TEST_CASE("--help of the program and of every command") {
  for (const std::string cmd : {"plan", "generate", "encode", "decode", "info", "convert"}) {
    const Result r = cli({cmd, "--help"});
    INFO(cmd);
    CHECK(r.rc == 0);
    CHECK(has(r.out, "usage: epona " + cmd));
    CHECK(has(r.out, "--quiet"));
    CHECK(r.err.empty());
    CHECK(cli({cmd, "-h"}).out == r.out);
  }
  const Result top = cli({"--help"});
  CHECK(top.rc == 0);
  for (const std::string cmd : {"plan", "generate", "encode", "decode", "info", "convert"}) CHECK(has(top.out, "  " + cmd));
  CHECK(cli({"--version"}).out == std::string("epona ") + app::kVersion + "\n");
}

TEST_CASE("info on the golden checkpoints: counts, keys, the detected configuration") {
  const std::string world = golden_dir() + "/weights_world.safetensors", dcae = golden_dir() + "/weights_dcae.safetensors";
  const Result r = cli({"info", world, dcae, "--keys", "--config", golden_dir() + "/configs.json", "-q"});
  REQUIRE(r.rc == 0);
  CHECK(r.err.empty());
  for (const auto& path : {world, dcae}) {
    const auto m = io::load_safetensors(path);
    CHECK(has(r.out, "tensors: " + std::to_string(m.size()) + ","));
    for (const auto& [name, t] : m.entries())
      CHECK(has(r.out, "    " + name + "  " + std::string(dtype_name(t.dtype)) + "  " + shape_str(t.shape) + "\n"));
  }
  const auto& w = golden_configs().world;
  CHECK(has(r.out, "MST width n_embd = " + std::to_string(w.n_embd) + " "));
  CHECK(has(r.out, "MST blocks n_layer[0] = " + std::to_string(w.n_layer[0]) + " "));
  CHECK(has(r.out, "VisDiT heads = " + std::to_string(w.n_head_dit) + " "));
  CHECK(has(r.out, "TrajDiT heads = " + std::to_string(w.n_head_dit_traj) + " "));
  CHECK(has(r.out, "matches " + golden_dir() + "/configs.json"));
  CHECK(has(r.out, "(match)"));
  CHECK_FALSE(has(r.out, "MISMATCH"));
  CHECK_FALSE(has(r.out, "differs from"));
  CHECK_FALSE(has(r.out, "cannot read"));
}

TEST_CASE("info --write-config gives back the configuration the shapes imply") {
  TempDir t;
  const std::string world = golden_dir() + "/weights_world.safetensors", dcae = golden_dir() + "/weights_dcae.safetensors";
  // Against the golden configuration every readable value agrees, so the file equals it.
  Result r = cli({"info", world, dcae, "--config", golden_dir() + "/configs.json", "--write-config", t / "same.json"});
  REQUIRE(r.rc == 0);
  CHECK(io::load_configs(t / "same.json") == golden_configs());
  // Against the shipped configuration the widths and depths come from the shapes (a copy away
  // from the configs.json beside the golden weights, which info would compare with).
  fs::copy_file(world, t.path / "alone.safetensors");
  r = cli({"info", t / "alone.safetensors", "--write-config", t / "detected.json"});
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "differs from the shipped Epona configuration in:"));
  CHECK(has(r.out, "n_embd: " + std::to_string(golden_configs().world.n_embd) + " (checkpoint) vs 2048 (configuration)"));
  const auto j = nlohmann::json::parse(read_file(t / "detected.json"));
  const auto& w = golden_configs().world;
  CHECK(j["world_model_config"]["n_embd"] == w.n_embd);
  CHECK(j["world_model_config"]["n_layer"] == nlohmann::json(w.n_layer));
  CHECK(j["world_model_config"]["n_embd_dit_traj"] == w.n_embd_dit_traj);
  CHECK(j["world_model_config"]["n_head"] == WorldModelConfig{}.n_head);  // assumed: not in the shapes
}

TEST_CASE("info reads the official .pkl form of the golden weights") {
  const std::string dir = std::string(EPONA_TEST_DATA_DIR) + "/pkl/";
  const Result r = cli({"info", dir + "weights_world.pkl", dir + "weights_dcae.pkl", "--config",
                        std::string(EPONA_GOLDEN_DEFAULT_DIR) + "/configs.json", "-q"});
  REQUIRE(r.rc == 0);
  CHECK(has(r.out, "format: PyTorch checkpoint (torch.save ZIP)"));
  CHECK(has(r.out, "BatchNorm buffer elements"));
  CHECK(has(r.out, "(match)"));
  CHECK_FALSE(has(r.out, "MISMATCH"));
  CHECK_FALSE(has(r.out, "differs from"));
}

TEST_CASE("convert: the official .pkl to safetensors, same names, dtypes, shapes and bytes") {
  TempDir t;
  const std::string pkl = std::string(EPONA_TEST_DATA_DIR) + "/pkl/weights_dcae.pkl";
  const Result r = cli({"convert", pkl, t / "dcae.safetensors", "-q"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  const auto from_pkl = io::load_weights(pkl);
  const auto file = io::read_safetensors(t / "dcae.safetensors");
  CHECK(file.metadata.at("converted_from") == "weights_dcae.pkl");
  REQUIRE(file.tensors.size() == from_pkl.size());
  for (const auto& [name, a] : from_pkl.entries()) {
    INFO(name);
    REQUIRE(file.tensors.contains(name));
    const auto& b = file.tensors.at(name);
    CHECK(a.dtype == b.dtype);
    CHECK(a.shape == b.shape);
    CHECK(std::equal(a.bytes.begin(), a.bytes.end(), b.bytes.begin(), b.bytes.end()));
  }
  check_cli_error(cli({"convert", pkl, t / "out.bin"}), "the name must end in .safetensors");
  check_cli_error(cli({"convert", t / "missing.pkl", t / "x.safetensors"}), "no such file");
  check_cli_error(cli({"convert", pkl, t / "x.safetensors", "--key", "optimizer"}), "optimizer");
}

TEST_CASE("encode and decode equal the DC-AE called directly") {
  TempDir t;
  const auto& cfg = golden_configs();
  write_file(t.path / "note.txt", "not an image");  // ignored inside folders
  const std::string frame = std::string(EPONA_TEST_DATA_DIR) + "/demo/frame_01.png";
  const std::vector<std::string> model = {"--dcae", golden_dir() + "/weights_dcae.safetensors", "--config",
                                          golden_dir() + "/configs.json", "-q"};
  auto with = [&](std::vector<std::string> a) {
    a.insert(a.end(), model.begin(), model.end());
    return a;
  };
  Result r = cli(with({"encode", frame, "-o", t / "z.npy"}));
  INFO(r.err);
  REQUIRE(r.rc == 0);
  const Tensor<float> z = io::read_npy<float>(t / "z.npy").values;
  const io::Image img = demo_frame(1);
  CHECK(z.shape() == Shape{1, cfg.dcae.latent_channels, img.height / 32, img.width / 32});
  cpu::Context ctx;
  const auto dcae = Dcae<Cpu, float>::load(io::load_safetensors(golden_dir() + "/weights_dcae.safetensors"), cfg.dcae);
  Tensor<float> x({1, 3, img.height, img.width});  // (u / 255 - 0.5) * 2, written out here
  for (std::int64_t c = 0; c < 3; ++c)
    for (std::int64_t y = 0; y < img.height; ++y)
      for (std::int64_t xx = 0; xx < img.width; ++xx)
        x.at(0, c, y, xx) = (static_cast<float>(img.at(y, xx, static_cast<int>(c))) / 255.0f - 0.5f) * 2.0f;
  check_same(z, dcae.encode(ctx, x));

  r = cli(with({"decode", t / "z.npy", "-o", t / "dec"}));
  REQUIRE(r.rc == 0);
  check_png(t / "dec/frame_0000.png", img.height, img.width);
  const io::Image expected = io::tensor_to_image(dcae.decode(ctx, z, false));
  CHECK(io::read_image(t / "dec/frame_0000.png").rgb == expected.rgb);

  // A folder: every image in natural order; sizes other than multiples of 32 need --size/--fit.
  r = cli(with({"encode", std::string(EPONA_TEST_DATA_DIR) + "/demo", "-o", t / "all.npy"}));
  REQUIRE(r.rc == 0);
  CHECK(io::read_npy<float>(t / "all.npy").values.size(0) == 3);
  r = cli(with({"encode", frame, "--size", "32x64", "--fit", "resize", "-o", t / "small.npy"}));
  REQUIRE(r.rc == 0);
  CHECK(io::read_npy<float>(t / "small.npy").values.shape() == Shape{1, cfg.dcae.latent_channels, 1, 2});
  check_cli_error(cli(with({"encode", frame, "--size", "32x64", "-o", t / "x.npy"})), "--fit resize|crop|cover");
  check_cli_error(cli(with({"encode", t / "missing.png"})), "no such file or folder");
  check_cli_error(cli(with({"encode", t / "note.txt"})), "not a PNG or JPEG file");
  io::write_npy(t / "flat.npy", Tensor<float>::zeros({4, 5}));
  check_cli_error(cli(with({"decode", t / "flat.npy", "-o", t / "d2"})), "latents must be (N, C, h, w)");
  Tensor<float> odd = z.clone();
  odd.data()[3] = std::nanf("");
  io::write_npy(t / "nan.npy", odd);
  check_cli_error(cli(with({"decode", t / "nan.npy", "-o", t / "d3"})), "non-finite latent value at flat index 3");
}

TEST_CASE("plan on the bundled demo: outputs exist, sizes, equal to WorldModel::plan") {
  TempDir t;
  const Result r = cli({"plan", "--out", t / "plan", "--seed", "7"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  const io::ModelConfigs demo = io::load_configs(std::string(EPONA_TEST_DATA_DIR) + "/golden/configs.json");
  const std::int64_t k = (app::kPlanMinHeight + demo.world.image_h - 1) / demo.world.image_h;  // small frames enlarged
  check_png(t / "plan/plan.png", k * demo.world.image_h, k * demo.world.image_w);
  CHECK(has(r.out, "plan.png (" + std::to_string(k * demo.world.image_h) + "x" + std::to_string(k * demo.world.image_w)));
  const Tensor<float> json = io::read_trajectory(t / "plan/trajectory.json");
  const Tensor<float> csv = io::read_trajectory(t / "plan/trajectory.csv");
  CHECK(json.shape() == Shape{1, demo.world.traj_len, 3});
  check_same(json, csv);
  CHECK(has(r.out, "wrote " + (t / "plan/plan.png")));

  // The same computation through the library.
  cpu::Context ctx;
  const std::string g = std::string(EPONA_TEST_DATA_DIR) + "/golden/";
  const auto dcae = Dcae<Cpu, float>::load(io::load_safetensors(g + "weights_dcae.safetensors"), demo.dcae);
  auto wm = WorldModel<Cpu, float>::load(io::load_safetensors(g + "weights_world.safetensors"), demo.world);
  const fs::path clip = std::string(EPONA_TEST_DATA_DIR) + "/demo";
  const History h = history_of(ctx, dcae, clip, io::load_poses(clip / "poses.csv"));
  SampleOptions opt;
  opt.seed = 7;
  check_same(json, wm.plan(h, opt));
  // The picture is the (enlarged) last frame with the plan drawn on it: some pixels changed.
  const io::Image last = app::enlarge(demo_frame(2), k), drawn = io::read_image(t / "plan/plan.png");
  std::int64_t changed = 0;
  for (std::size_t i = 0; i < last.rgb.size(); ++i) changed += last.rgb[i] != drawn.rgb[i];
  CHECK(changed > 0);
  CHECK(changed < static_cast<std::int64_t>(last.rgb.size()) / 2);
}

TEST_CASE("generate 2 frames: files and sizes, equal to rollout(), deterministic, replayable") {
  TempDir t;
  const auto& cfg = golden_configs();
  const fs::path clip = make_clip(t, cfg.world.condition_frames + 1, cfg.world.condition_frames + 1);
  std::vector<std::string> args = two_frames_of(clip);
  auto run_into = [&](const std::string& out) {
    auto a = args;
    a.insert(a.end(), {"--out", out});
    return cli(a);
  };
  const Result r = run_into(t / "g1");
  INFO(r.err);
  REQUIRE(r.rc == 0);
  const auto& w = cfg.world;
  check_png(t / "g1/frames/frame_0000.png", w.image_h, w.image_w);
  check_png(t / "g1/frames/frame_0001.png", w.image_h, w.image_w);
  CHECK_FALSE(fs::exists(t / "g1/frames/frame_0002.png"));
  CHECK_FALSE(fs::exists(t / "g1/INCOMPLETE"));  // the note of a run in progress is gone at the end
  const auto layout = app::SheetLayout::of(w.condition_frames + 2, w.image_h, w.image_w);
  check_png(t / "g1/contact_sheet.png", layout.height(), layout.width());
  const Tensor<float> traj = io::read_trajectory(t / "g1/trajectory.csv");
  CHECK(traj.shape() == Shape{2, w.traj_len, 3});
  check_same(traj, io::read_trajectory(t / "g1/trajectory.json"));
  // poses.csv holds waypoint 0 of each step: the motion into each generated frame.
  const io::PoseSequence motions = io::load_poses(t / "g1/poses.csv");
  REQUIRE(motions.size() == 2);
  for (std::int64_t s = 0; s < 2; ++s) {
    CHECK(motions.x[std::size_t(s)] == traj.at(s, 0, 0));
    CHECK(motions.yaw[std::size_t(s)] == traj.at(s, 0, 2));
  }

  // The library's rollout on the same window and seed gives the same latents and plans.
  cpu::Context ctx;
  const auto dcae = Dcae<Cpu, float>::load(io::load_safetensors(golden_dir() + "/weights_dcae.safetensors"), cfg.dcae);
  auto wm = WorldModel<Cpu, float>::load(io::load_safetensors(golden_dir() + "/weights_world.safetensors"), w);
  RolloutOptions opt;
  opt.frames = 2;
  opt.sample.steps = 2;
  opt.sample.seed = 3;
  const RolloutResult ref = rollout(wm, history_of(ctx, dcae, clip, io::load_poses(clip / "poses.csv")), opt);
  check_same(traj, ref.trajectories.reshape({2, w.traj_len, 3}));
  const Tensor<float> latents = io::read_npy<float>(t / "g1/latents.npy").values;
  check_same(latents, tokens_to_latent(ctx, ref.latents.reshape({2, w.img_tokens(), w.token_dim()}), w.latent_h(), w.latent_w()));

  // Same seed, same inputs: identical bytes.
  REQUIRE(run_into(t / "g2").rc == 0);
  for (const std::string f : {"frames/frame_0000.png", "frames/frame_0001.png", "contact_sheet.png", "trajectory.csv",
                              "trajectory.json", "poses.csv", "latents.npy"})
    CHECK_MESSAGE(read_file(t.path / "g1" / f) == read_file(t.path / "g2" / f), f);

  // Replaying the log drives each step with its logged waypoint 0.
  auto replay = args;
  replay.insert(replay.end(), {"--trajectory", t / "g1/trajectory.csv", "--out", t / "g3", "--decode", "frame"});
  replay.erase(std::find(replay.begin(), replay.end(), "-n"), std::find(replay.begin(), replay.end(), "-n") + 2);
  const Result rr = cli(replay);
  INFO(rr.err);
  REQUIRE(rr.rc == 0);
  const io::PoseSequence used = io::load_poses(t / "g3/poses.csv");
  CHECK(used.x == motions.x);
  CHECK(used.y == motions.y);
  CHECK(used.yaw == motions.yaw);
  CHECK(io::read_trajectory(t / "g3/trajectory.csv").shape() == Shape{2, 1, 3});
  check_png(t / "g3/frames/frame_0001.png", w.image_h, w.image_w);
  auto too_many = replay;
  too_many.insert(too_many.end(), {"-n", "3"});
  check_cli_error(cli(too_many), "holds 2 action(s); --num-frames asks for 3");
}

// --tensor-parallel N (docs/parallel.md): the VisDiT split over threads on the CPU. The TrajDiT is
// whole on every shard, so the plans are the same bytes; the latents within float32 rounding of the
// whole model's (a shard adds its part of each product, the group adds the parts), the frames within
// one 8-bit level.
TEST_CASE("--tensor-parallel 2: plan and generate as the whole model; splits that do not divide are refused") {
  TempDir t;
  const auto& cfg = golden_configs();
  const fs::path clip = make_clip(t, cfg.world.condition_frames + 1, cfg.world.condition_frames + 1);
  std::vector<std::string> args = two_frames_of(clip);
  const auto run = [&](const std::string& out, std::vector<std::string> extra) {
    auto a = args;
    a.insert(a.end(), {"--out", out});
    a.insert(a.end(), extra.begin(), extra.end());
    return cli(a);
  };
  const Result whole = run(t / "whole", {}), split = run(t / "split", {"--tensor-parallel", "2"});
  INFO(split.err);
  REQUIRE(whole.rc == 0);
  REQUIRE(split.rc == 0);
  // Step 0's plan comes before any split work: the same numbers. Step 1's plan sees frame 0.
  const Tensor<float> plans = io::read_trajectory(t / "whole/trajectory.csv");
  const Tensor<float> split_plans = io::read_trajectory(t / "split/trajectory.csv");
  check_same(plans.slice(0, 1), split_plans.slice(0, 1));
  const auto worst_rel = [](const Tensor<float>& x, const Tensor<float>& y) {
    REQUIRE(x.shape() == y.shape());
    double worst = 0, scale = 0;
    for (std::int64_t i = 0; i < x.numel(); ++i) {
      worst = std::max(worst, std::abs(double(x.data()[i]) - y.data()[i]));
      scale = std::max(scale, std::abs(double(x.data()[i])));
    }
    return worst / scale;
  };
  const double latents = worst_rel(io::read_npy<float>(t / "whole/latents.npy").values,
                                   io::read_npy<float>(t / "split/latents.npy").values);
  const double step1 = worst_rel(plans, split_plans);
  MESSAGE("--tensor-parallel 2: latents within ", latents, " (relative to their largest), plans within ", step1);
  CHECK(latents <= 1e-5);
  CHECK(step1 <= 1e-4);
  for (const std::string f : {"frames/frame_0000.png", "frames/frame_0001.png"}) {
    const io::Image x = io::read_image((t.path / "whole" / f).string()), y = io::read_image((t.path / "split" / f).string());
    REQUIRE(x.rgb.size() == y.rgb.size());
    int most = 0;
    for (std::size_t i = 0; i < x.rgb.size(); ++i) most = std::max(most, std::abs(int(x.rgb[i]) - int(y.rgb[i])));
    CHECK_MESSAGE(most <= 1, f);
  }

  const Result plan = cli({"plan", "--out", t / "plan", "--seed", "7"});
  const Result plan_split = cli({"plan", "--out", t / "plan_split", "--seed", "7", "--tensor-parallel", "2"});
  REQUIRE(plan.rc == 0);
  REQUIRE(plan_split.rc == 0);
  CHECK(read_file(t.path / "plan/trajectory.json") == read_file(t.path / "plan_split/trajectory.json"));

  check_cli_error(run(t / "three", {"--tensor-parallel", "3"}), "do not split evenly over 3 shards");
  check_cli_error(run(t / "none", {"--tensor-parallel", "0"}), "--tensor-parallel");
  check_cli_error(run(t / "many", {"--tensor-parallel", "9"}), "--tensor-parallel");
  // How GPUs add up their parts means nothing to the CPU's threads.
  check_cli_error(run(t / "peer", {"--tensor-parallel", "2", "--shard-sum", "peer"}), "applies to --backend cuda");
  check_cli_error(run(t / "bogus", {"--tensor-parallel", "2", "--shard-sum", "mpi"}), "--shard-sum");
  CHECK_FALSE(fs::exists(t / "three/frames/frame_0000.png"));
}

TEST_CASE("generate on the bundled demo; progress on stderr unless --quiet") {
  TempDir t;
  Result r = cli({"generate", "-n", "2", "--steps", "2", "--out", t / "demo"});
  INFO(r.err);
  REQUIRE(r.rc == 0);
  CHECK(has(r.err, "generate [########################] 2/2 frames"));
  CHECK(has(r.err, "elapsed"));
  CHECK((has(r.err, "frame/s") || has(r.err, "s/frame")));
  const io::ModelConfigs demo = io::load_configs(std::string(EPONA_TEST_DATA_DIR) + "/golden/configs.json");
  check_png(t / "demo/frames/frame_0001.png", demo.world.image_h, demo.world.image_w);
  r = cli({"generate", "-n", "1", "--steps", "1", "--out", t / "quiet", "--quiet"});
  REQUIRE(r.rc == 0);
  CHECK(r.err.empty());
  CHECK(has(r.out, "wrote"));
}

TEST_CASE("bad inputs: clear errors, exit 1") {
  TempDir t;
  const auto& w = golden_configs().world;
  auto plan = [&](const std::vector<std::string>& extra) {
    std::vector<std::string> a = {"plan", "--steps", "1", "--out", t / "out", "-q"};
    const auto model = golden_model_args();
    a.insert(a.end(), model.begin(), model.end());
    a.insert(a.end(), extra.begin(), extra.end());
    return cli(a);
  };
  check_cli_error(plan({"--frames", t / "nowhere", "--poses", t / "p.csv"}), "no such folder");
  check_cli_error(plan({}), "--frames DIR is needed with --weights");
  {
    TempDir c;
    const fs::path clip = make_clip(c, w.condition_frames - 1, w.condition_frames - 1);
    check_cli_error(plan({"--frames", clip.string(), "--poses", (clip / "poses.csv").string()}),
                "the model needs " + std::to_string(w.condition_frames) + " condition frames, the folder holds " +
                    std::to_string(w.condition_frames - 1));
  }
  {
    TempDir c;
    const fs::path clip = make_clip(c, w.condition_frames, w.condition_frames + 1);
    check_cli_error(plan({"--frames", clip.string(), "--poses", (clip / "poses.csv").string()}), "give one pose per frame");
  }
  {
    TempDir c;
    const fs::path clip = make_clip(c, w.condition_frames, w.condition_frames, "2.0,nan,0.0");
    check_cli_error(plan({"--frames", clip.string(), "--poses", (clip / "poses.csv").string()}), "is not a finite number");
  }
  {
    TempDir c;
    const fs::path clip = make_clip(c, w.condition_frames, w.condition_frames);
    io::write_png((clip / "f0.png").string(), io::resize_bicubic(demo_frame(0), w.image_h + 32, w.image_w));
    const std::vector<std::string> in = {"--frames", clip.string(), "--poses", (clip / "poses.csv").string()};
    check_cli_error(plan(in), "--fit resize|crop|cover");
    auto fitted = in;
    fitted.insert(fitted.end(), {"--fit", "resize"});
    CHECK(plan(fitted).rc == 0);
    fitted.insert(fitted.end(), {"--dtype", "bf16"});
    CHECK(plan(fitted).rc == 0);  // bf16 weights run too
  }
  check_cli_error(cli({"plan", "--weights", t / "none.pkl", "--dcae", t / "none.pkl"}), "no such file");
  {
    TempDir c;
    const fs::path clip = make_clip(c, w.condition_frames, w.condition_frames);
    check_cli_error(cli({"plan", "--weights", golden_dir() + "/weights_world.safetensors", "--dcae",
                     golden_dir() + "/weights_world.safetensors", "--config", golden_dir() + "/configs.json",
                     "--frames", clip.string(), "--poses", (clip / "poses.csv").string()}),
                "holds no DC-AE weights (no 'encoder.*' keys; it is a world-model checkpoint)");
  }
  // Weights that do not fit the configuration: the binding names the problem and the values the
  // checkpoint's shapes imply. DC-AE: the golden weights with the shipped DcaeConfig{}.
  const Result dcae_mismatch = cli({"encode", std::string(EPONA_TEST_DATA_DIR) + "/demo/frame_00.png", "--dcae",
                                    golden_dir() + "/weights_dcae.safetensors", "-o", t / "z.npy", "-q"});
  check_cli_error(dcae_mismatch, "the checkpoint's shapes differ from the shipped Epona configuration in");
  CHECK(has(dcae_mismatch.err, "--write-config"));
  {  // World model: the golden configuration with a wider MST.
    TempDir c;
    auto j = nlohmann::json::parse(read_file(golden_dir() + "/configs.json"));
    j["world_model_config"]["n_embd"] = 2 * w.n_embd;
    write_file(c.path / "wide.json", j.dump());
    const fs::path clip = make_clip(c, w.condition_frames, w.condition_frames);
    const Result r = cli({"plan", "--weights", golden_dir() + "/weights_world.safetensors", "--dcae",
                          golden_dir() + "/weights_dcae.safetensors", "--config", c / "wide.json", "--frames",
                          clip.string(), "--poses", (clip / "poses.csv").string(), "-q"});
    check_cli_error(r, "n_embd: " + std::to_string(w.n_embd) + " (checkpoint) vs " + std::to_string(2 * w.n_embd) +
                       " (configuration)");
    CHECK(has(r.err, "weight problem(s)"));
  }
  check_cli_error(cli({"info", t / "absent.safetensors"}), "no such file");
  check_cli_error(cli({"info", std::string(EPONA_TEST_DATA_DIR) + "/pkl/no_state_dict.pkl"}), "pass the key explicitly");
  check_cli_error(cli({"info", std::string(EPONA_TEST_DATA_DIR) + "/pkl/hostile_os_system.pkl"}), "os.system");
  write_file(t.path / "junk.safetensors", "not a checkpoint at all");
  check_cli_error(cli({"info", t / "junk.safetensors"}), "junk.safetensors");
}

// generate --clips: clip i of the set is what generate of that clip alone with seed + i writes.
TEST_CASE("generate --clips: each clip as generate of it alone, seed + clip index") {
  TempDir t;
  const auto& w = golden_configs().world;
  const fs::path clip = make_clip(t, w.condition_frames, w.condition_frames);
  for (const char* name : {"a", "b"}) {  // two clip folders of the same frames: only the seed differs
    fs::create_directories(t.path / "set" / name);
    fs::copy(clip, t.path / "set" / name / "frames");
    fs::rename(t.path / "set" / name / "frames" / "poses.csv", t.path / "set" / name / "poses.csv");
  }
  const auto run = [&](std::vector<std::string> a) {
    a.insert(a.begin(), {"generate", "-n", "1", "--steps", "2", "-q"});
    for (const auto& m : golden_model_args()) a.push_back(m);
    return cli(a);
  };
  const Result set = run({"--clips", t / "set", "--seed", "5", "--out", t / "many"});
  INFO(set.err);
  REQUIRE(set.rc == 0);
  CHECK(has(set.out, "generated 1 frame for each of 2 clips"));
  for (const auto& [name, seed] : {std::pair{"a", "5"}, std::pair{"b", "6"}}) {
    const fs::path alone = t.path / (std::string("alone_") + name);
    const Result r = run({"--frames", (t.path / "set" / name / "frames").string(), "--poses",
                          (t.path / "set" / name / "poses.csv").string(), "--seed", seed, "--out", alone.string()});
    REQUIRE(r.rc == 0);
    CHECK(read_file((t.path / "many" / name / "trajectory.json").string()) == read_file((alone / "trajectory.json").string()));
    CHECK(read_file((t.path / "many" / name / "frames/frame_0000.png").string()) ==
          read_file((alone / "frames/frame_0000.png").string()));
  }
  CHECK(read_file((t.path / "many/a/trajectory.json").string()) != read_file((t.path / "many/b/trajectory.json").string()));
  check_cli_error(run({"--clips", t / "set", "--frames", clip.string()}), "--clips and --frames do not go together");
  check_cli_error(run({"--clips", t / "absent"}), "no such folder");
}

// Issue #39: generate --clips --batch 2 rolls two clips out per world-model call; each clip keeps
// seed + i, so it writes what --batch 1 writes, up to the rounding of the batched matrix products.
TEST_CASE("generate --clips --batch 2: the trajectories and frames of --batch 1") {
  TempDir t;
  const auto& w = golden_configs().world;
  const fs::path clip = make_clip(t, w.condition_frames, w.condition_frames);
  const std::vector<std::string> names{"a", "b", "c"};  // 3 clips: a batch of 2 and a batch of 1
  for (const auto& name : names) {
    fs::create_directories(t.path / "set" / name);
    fs::copy(clip, t.path / "set" / name / "frames");
    fs::rename(t.path / "set" / name / "frames" / "poses.csv", t.path / "set" / name / "poses.csv");
  }
  const auto run = [&](const std::string& batch, const std::string& out) {
    std::vector<std::string> a{"generate", "-n", "2", "--steps", "2", "-q", "--seed", "9", "--clips", t / "set",
                               "--batch", batch, "--out", t / out};
    for (const auto& m : golden_model_args()) a.push_back(m);
    return cli(a);
  };
  const Result one = run("1", "one"), two = run("2", "two");
  INFO(two.err);
  REQUIRE(one.rc == 0);
  REQUIRE(two.rc == 0);
  CHECK(has(two.out, "(a batch of 2 clips)"));
  double worst_traj = 0;
  int worst_pixel = 0;
  for (const auto& name : names) {
    const Tensor<float> a = io::read_trajectory(t.path / "one" / name / "trajectory.json");
    const Tensor<float> b = io::read_trajectory(t.path / "two" / name / "trajectory.json");
    REQUIRE(a.shape() == b.shape());
    float scale = 0;
    for (std::int64_t i = 0; i < a.numel(); ++i) scale = std::max(scale, std::abs(a.data()[i]));
    for (std::int64_t i = 0; i < a.numel(); ++i)
      worst_traj = std::max(worst_traj, double(std::abs(a.data()[i] - b.data()[i])) / double(scale));
    for (const char* frame : {"frame_0000.png", "frame_0001.png"}) {
      const io::Image x = io::read_image((t.path / "one" / name / "frames" / frame).string());
      const io::Image y = io::read_image((t.path / "two" / name / "frames" / frame).string());
      REQUIRE(x.rgb.size() == y.rgb.size());
      for (std::size_t i = 0; i < x.rgb.size(); ++i) worst_pixel = std::max(worst_pixel, std::abs(int(x.rgb[i]) - int(y.rgb[i])));
    }
  }
  MESSAGE("generate --batch 2 vs --batch 1: worst trajectory difference ", worst_traj, " of the largest value, worst pixel ",
          worst_pixel, " level(s)");
  CHECK(worst_traj <= 1e-5);
  CHECK(worst_pixel <= 1);  // rounding: at most one 8-bit level
  CHECK(read_file(t.path / "one/a/trajectory.json") != read_file(t.path / "one/b/trajectory.json"));  // seeds differ
  check_cli_error(run("0", "zero"), "--batch must be in [1, 64], got 0");
  std::vector<std::string> single{"generate", "-n", "1", "--frames", clip.string(), "--poses", (clip / "poses.csv").string(),
                                  "--batch", "2", "--out", t / "single"};
  for (const auto& m : golden_model_args()) single.push_back(m);
  check_cli_error(cli(single), "--batch is for --clips");
}

// An epona built without FFmpeg (where libavcodec is missing) refuses --video before any work and
// says how to get it. The test programs share one build of the commands, with FFmpeg where the
// machine has it, so the refusal is asked for directly.
TEST_CASE("--video without FFmpeg: refused with what to install") {
  app::ArgParser parser("generate", "", "");
  app::add_video_options(parser, "the frames");
  const auto args = parser.parse({"--video", "clip.mp4"});
  try {
    (void)app::video_request(args, "", false);
    FAIL("--video was accepted by a build without FFmpeg");
  } catch (const std::exception& e) {
    CHECK(has(e.what(), "--video: this epona was built without FFmpeg (libavcodec); install libavcodec-dev"));
  }
  CHECK_FALSE(app::video_request(parser.parse({}), "", false).has_value());  // no --video: nothing to refuse
}

// Issue #40: a launcher's variables as mpirun sets them. This test program is built without MPI
// (EPONA_APP_MPI is the epona program's), so eval refuses with how to get MPI; commands that do
// not split their work refuse first, in any build (tests/apps/mpi_eval.cpp runs the real mpirun).
TEST_CASE("several processes: refused without MPI, and by commands that do not split their work") {
  test::TempDir t("epona_cli_mpi");
  ::setenv("OMPI_COMM_WORLD_SIZE", "2", 1);
  ::setenv("OMPI_COMM_WORLD_RANK", "1", 1);
  const Result plan = cli({"plan", "-q", "--out", t / "plan"});
  const Result one_clip = cli({"generate", "-q", "-n", "1", "--out", t / "one"});
  const Result eval = cli({"eval", "--clips", t / "none", "--json", t / "r.json", "-q"});
  ::setenv("OMPI_COMM_WORLD_SIZE", "many", 1);
  const Result garbled = cli({"eval", "--clips", t / "none", "--json", t / "r.json", "-q"});
  ::unsetenv("OMPI_COMM_WORLD_SIZE");
  ::unsetenv("OMPI_COMM_WORLD_RANK");
  check_cli_error(plan, "plan runs as one process, but openmpi started 2 (this is rank 1)");
  CHECK_FALSE(fs::exists(t.path / "plan"));
  check_cli_error(one_clip, "generate of one clip runs as one process, but openmpi started 2 (this is rank 1)");
  CHECK_FALSE(fs::exists(t.path / "one"));
  check_cli_error(eval, "openmpi started 2 processes (this is rank 1), but this epona was built without MPI");
  check_cli_error(garbled, "OMPI_COMM_WORLD_SIZE is not a process count or index: 'many'");
}

// The one translation unit of this program that compiles stb (after every other include).
#include "epona/io/stb_implementation.hpp"
