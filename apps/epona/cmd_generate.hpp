// apps/epona/cmd_generate.hpp — `epona generate`: rolls the world model out for N frames, each
// step conditioned on the sliding window of the last F frames, driven by its own planned
// trajectory (waypoint 0 of each step, as test_free.py) or by actions read from a file; frames
// are decoded in clips of the DC-AE's temporal length as test_nuplan.py does (or one by one).
#pragma once

#include <cstdio>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "args.hpp"
#include "cmd_common.hpp"
#include "console.hpp"
#include "drawing.hpp"
#include "engine.hpp"
#include "frames.hpp"
#include "models.hpp"
#include "rollout_common.hpp"
#include "processes.hpp"
#include "video_output.hpp"
#include "epona/domain/trajectory_io.hpp"
#include "epona/eval/clip_set.hpp"
#include "epona/io/image.hpp"
#include "epona/io/npy.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/rollout.hpp"

namespace epona::app {

inline constexpr std::int64_t kSheetTiles = 40;  // input frames + a sample of the generated ones

inline ArgParser generate_parser() {
  ArgParser p("epona generate", "[options]",
              "Rolls the world model out: each step predicts the next frame from the last F frames and the\n"
              "motion into it, then the window slides. The motion is the model's own plan (waypoint 0 of\n"
              "each step's trajectory) or, with --trajectory, one action per step from a file. Writes\n"
              "frames/frame_NNNN.png, contact_sheet.png, trajectory.json/.csv (each step's plan, or the\n"
              "actions used) and poses.csv (the motion into each generated frame) into the output folder;\n"
              "with --video also an MP4 of the input frames followed by the generated ones.\n"
              "Without --weights it runs the bundled model (models/small-synthetic) on its demo clip.");
  add_model_options(p, true, true);
  add_clip_options(p);
  p.option("clips", "DIR", "roll out every clip folder of DIR (frames/ + poses.csv each, as `epona synth` writes) "
           "into OUT/<clip>/, the weights loaded once; clip i uses seed + i. Under mpirun or srun the clips are "
           "split over the processes", "one clip: --frames and --poses")
      .option("num-frames", "N", "frames to generate", "6, or one per action of --trajectory", 'n')
      .option("trajectory", "FILE", "actions to follow: a trajectory written by epona (waypoint 0 of each step) "
              "or a poses file (one motion per step)")
      .option("max-frames", "N", "refuse to roll out more frames than this", "10000")
      .option("decode", "MODE", "clip: clips of the DC-AE's temporal length (video mode, as test_nuplan.py); "
              "frame: each frame alone", "clip")
      .flag("latents", "also write latents.npy, (N, C, h, w), for `epona decode`");
  add_video_options(p, "the input frames followed by the generated ones");
  add_sampling_options(p);
  add_batch_option(p, "clips of --clips");
  add_compute_options(p);
  add_output_options(p, "out/generate");
  p.epilog("examples:\n"
           "  epona generate -n 4                          # the bundled model and clip\n"
           "  epona generate --weights world.pkl --dcae dcae_td_20000.pkl --frames clip/ \\\n"
           "                 --poses clip/poses.csv -n 60 --steps 100 --out out/drive\n"
           "  epona generate ... --trajectory out/drive/trajectory.csv   # replay the same actions\n"
           "  epona generate -n 20 --video out/drive.mp4 --fps 10         # and a video of it all");
  return p;
}

// Writes decoded frames as they complete (into the video too, when one is written) and keeps
// the ones the contact sheet shows.
class FrameSink final : public FrameConsumer {
 public:
  FrameSink(std::filesystem::path dir, std::vector<std::int64_t> sheet_picks, VideoOut* video = nullptr)
      : dir_(std::move(dir)), picks_(std::move(sheet_picks)), video_(video) {
    std::error_code ec;
    std::filesystem::create_directories(dir_, ec);
    EPONA_CHECK(std::filesystem::is_directory(dir_, ec), dir_.string(), ": cannot create the frames folder");
    remove_stale_frames();
  }
  void put(const io::Image& img) override {
    char name[32];
    std::snprintf(name, sizeof name, "frame_%04lld.png", static_cast<long long>(written_));
    io::write_png((dir_ / name).string(), img);
    if (video_) video_->put(img);
    if (next_pick_ < picks_.size() && picks_[next_pick_] == written_) {
      kept_.push_back({img, false, written_});
      ++next_pick_;
    }
    ++written_;
  }
  std::int64_t written() const { return written_; }
  const std::vector<SheetTile>& kept() const { return kept_; }
  const std::filesystem::path& dir() const { return dir_; }

 private:
  // frame_NNNN.png files of an earlier, longer run would read as part of this one.
  void remove_stale_frames() {
    std::error_code ec;
    std::vector<std::filesystem::path> stale;
    for (const auto& e : std::filesystem::directory_iterator(dir_, ec)) {
      const std::string name = e.path().filename().string();
      if (name.size() >= 14 && starts_with(name, "frame_") && ends_with(name, ".png") &&
          is_index(name.substr(6, name.size() - 10)))
        stale.push_back(e.path());
    }
    for (const auto& p : stale) std::filesystem::remove(p, ec);
  }

  std::filesystem::path dir_;
  std::vector<std::int64_t> picks_;
  std::size_t next_pick_ = 0;
  VideoOut* video_;
  std::int64_t written_ = 0;
  std::vector<SheetTile> kept_;
};

// The per-step actions of --trajectory, or none (self-predicted).
inline std::optional<io::PoseSequence> read_step_actions(const ParsedArgs& a) {
  if (!a.has("trajectory")) return std::nullopt;
  const std::string path = *a.get("trajectory");
  check_file(path, "--trajectory");
  return io::read_actions(path);
}

// Frames to roll out: --num-frames, or one per action of --trajectory; either way within
// --max-frames (a file of a million actions asked for a million frames).
inline std::int64_t frames_to_generate(const ParsedArgs& a, const std::optional<io::PoseSequence>& actions) {
  const std::int64_t limit = a.integer("max-frames", io::limits::kFrames, 1);
  const auto n = a.maybe_integer("num-frames", 1);
  if (n && *n > limit)
    usage_fail("--num-frames ", *n, " is more than the limit of ", limit, " frames (--max-frames raises it)");
  if (!actions) return n.value_or(6);
  const auto available = static_cast<std::int64_t>(actions->size());
  EPONA_CHECK(!n || *n <= available, "--trajectory ", *a.get("trajectory"), " holds ", available,
              " action(s); --num-frames asks for ", *n);
  EPONA_CHECK(n || available <= limit, "--trajectory ", *a.get("trajectory"), " holds ", available,
              " actions, more than the limit of ", limit,
              " frames (--num-frames N follows the first N; --max-frames raises the limit)");
  return n.value_or(available);
}

inline void print_generate_summary(std::ostream& out, const std::filesystem::path& dir, const WorldModelConfig& wc,
                                   std::int64_t N, double seconds, const io::Image& sheet, std::size_t inputs,
                                   std::size_t shown, bool given_actions, bool latents, const std::string& video) {
  char last[32];
  std::snprintf(last, sizeof last, "frame_%04lld.png", static_cast<long long>(N - 1));
  out << "generated " << counted(N, "frame") << " of " << wc.image_h << "x" << wc.image_w << " in "
      << duration_text(seconds) << "\n"
      << "wrote " << (dir / "frames" / "frame_0000.png").string() << (N > 1 ? std::string(" ... ") + last : "") << "\n"
      << "wrote " << (dir / "contact_sheet.png").string() << " (" << size_text(sheet) << ": " << inputs
      << " input frame(s) framed blue, " << shown << " generated framed orange, numbered)\n"
      << "wrote " << (dir / "trajectory.json").string() << ", " << (dir / "trajectory.csv").string() << " ("
      << (given_actions ? "the action of each step" : "each step's plan") << "), " << (dir / "poses.csv").string() << "\n";
  if (latents) out << "wrote " << (dir / "latents.npy").string() << "\n";
  if (!video.empty()) out << video << "\n";
}

// What one clip's rollout wrote, for the summary.
struct GeneratedClip {
  double seconds = 0;
  io::Image sheet;
  std::size_t inputs = 0, shown = 0;
  std::string video_line;
};

// One clip's outputs while it rolls out, in `dir` (marked INCOMPLETE until finish): the frames as
// they are decoded (and the video, when asked), then the contact sheet, trajectory, poses and
// latents. Several may roll out in one batch (roll_out_batch).
class ClipGeneration {
 public:
  ClipGeneration(Engine& engine, cpu::Context& ctx, const Clip& clip, const RolloutPlan& plan,
                 const std::filesystem::path& dir, const WorldModelConfig& wc,
                 const std::optional<VideoRequest>& video_to, const Console& con)
      : clip_(clip), plan_(plan), dir_(dir), incomplete_(dir, "epona generate") {
    if (!plan.keep_latents) remove_stale_output(dir / "latents.npy");
    remove_stale_frames(dir / "frames", plan.frames);
    window_ = model::make_window(ctx, encode_frames(engine, clip.frames, con), clip.poses);
    const auto slots = std::max<std::int64_t>(kSheetTiles - static_cast<std::int64_t>(clip.frames.size()), 5);
    if (video_to) {
      video_.emplace(*video_to, wc.image_h, wc.image_w);
      for (const auto& f : clip.frames) video_->put(f);
    }
    sink_.emplace(dir / "frames", sheet_picks(plan.frames, slots), video_ ? &*video_ : nullptr);
  }
  ClipGeneration(const ClipGeneration&) = delete;
  ClipGeneration& operator=(const ClipGeneration&) = delete;

  // This clip as a scene of a rollout (its window, the plan's seed and actions, its frame sink).
  RolloutItem item() { return {window_, plan_.seed, plan_.actions, &*sink_}; }

  // Writes what the rollout logged and marks the folder complete.
  GeneratedClip finish(cpu::Context& ctx, const RolloutLog& log, const WorldModelConfig& wc, double seconds) {
    GeneratedClip g;
    g.seconds = seconds;
    std::vector<SheetTile> tiles;
    const auto inputs = static_cast<std::int64_t>(clip_.frames.size());
    for (std::int64_t i = 0; i < inputs; ++i) tiles.push_back({clip_.frames[static_cast<std::size_t>(i)], true, i - inputs});
    tiles.insert(tiles.end(), sink_->kept().begin(), sink_->kept().end());
    g.sheet = contact_sheet(tiles);
    io::write_png((dir_ / "contact_sheet.png").string(), g.sheet);
    io::write_trajectory(dir_ / "trajectory.json", log.steps);
    io::write_trajectory(dir_ / "trajectory.csv", log.steps);
    write_pose_csv(dir_ / "poses.csv", log.motions);
    if (plan_.keep_latents)
      io::write_npy(dir_ / "latents.npy", tokens_to_latent(ctx, log.latents, wc.latent_h(), wc.latent_w()));
    g.video_line = video_ ? video_->finish() : std::string();
    incomplete_.done();
    g.inputs = clip_.frames.size(), g.shown = sink_->kept().size();
    return g;
  }

 private:
  const Clip& clip_;
  RolloutPlan plan_;
  std::filesystem::path dir_;
  IncompleteMarker incomplete_;
  History window_;
  std::optional<VideoOut> video_;
  std::optional<FrameSink> sink_;  // after video_: writes into it
};

// Rolls `clip` out under `plan` and writes every output into `dir` (marked INCOMPLETE until the
// end): frames, contact sheet, trajectory, poses, and latents and video when asked.
inline GeneratedClip generate_into(Engine& engine, cpu::Context& ctx, const Clip& clip, const RolloutPlan& plan,
                                   const std::filesystem::path& dir, const WorldModelConfig& wc,
                                   const std::optional<VideoRequest>& video_to, const Console& con) {
  ClipGeneration generation(engine, ctx, clip, plan, dir, wc, video_to, con);
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<RolloutItem> one{generation.item()};
  const RolloutLog log = std::move(roll_out_batch(engine, ctx, std::move(one), wc, plan, con).front());
  return generation.finish(ctx, log, wc, seconds_since(t0));
}

// The rollout settings of the command line (seed, samplers, actions, frames, decoding).
inline RolloutPlan rollout_plan(const ParsedArgs& a, const WorldModelConfig& wc) {
  RolloutPlan plan;
  const SampleOptions sample = sample_options(a, wc);
  plan.samplers = samplers_of(sample);
  plan.seed = sample.seed;
  plan.actions = read_step_actions(a);
  plan.frames = frames_to_generate(a, plan.actions);
  plan.keep_latents = a.flag("latents");
  return plan;
}

inline void note_rollout(const Console& con, const ParsedArgs& a, const RolloutPlan& plan, const std::string& what) {
  con.note("generating ", counted(plan.frames, "frame"), what, ": ", describe(plan.samplers, !plan.actions), ", seed ",
           plan.seed, ", ",
           plan.actions ? "actions from " + *a.get("trajectory") : std::string("self-predicted trajectory"), ", decoded ",
           plan.clip_len > 1 ? "in clips of " + std::to_string(plan.clip_len) : std::string("frame by frame"));
}

inline std::int64_t decode_clip_length(const ParsedArgs& a, const DcaeConfig& dc) {
  const bool clip_decode = a.choice("decode", {"clip", "frame"}, "clip") == "clip";
  return clip_decode && dc.add_decoder_temporal ? dc.condition_frames : 1;
}

// ---- many clips: generate --clips DIR ---------------------------------------------------------

// The clip folders of --clips (each with frames/ and poses.csv, as `epona synth` writes), every one
// read and checked before any work.
inline std::vector<eval::EvalClip> generation_clips(const ParsedArgs& a, const WorldModelConfig& wc) {
  std::vector<eval::EvalClip> clips;
  for (const auto& dir : eval::find_clip_folders(*a.get("clips"))) {
    clips.push_back(eval::read_clip(dir));
    eval::check_clip(clips.back(), {static_cast<std::size_t>(wc.condition_frames), 0, 0});
  }
  return clips;
}

// This process's share of the clips rolled out, clip i with seed + i, into out/<clip name>/, up to
// `batch` clips of the share rolled out together (one world-model call per frame; each clip's noise
// is what it draws alone); one summary line per clip.
inline std::string generate_share(const ParsedArgs& a, const std::vector<eval::EvalClip>& clips, const RolloutPlan& base,
                                  std::int64_t batch, const ModelFiles& files, const ComputeOptions& compute,
                                  const std::filesystem::path& out, const Job& job) {
  const Console& con = job.con;
  const WorldModelConfig& wc = files.configs.world;
  const auto engine = make_engine(compute);
  cpu::Context ctx(compute.threads);
  engine->load_dcae(files, con);
  engine->load_world(files, con);
  RolloutPlan plan = base;
  plan.clip_len = decode_clip_length(a, engine->dcae_config());
  const Console silent{con.out, con.err, true, false};
  const auto policy = size_policy(a.choice("fit", {"exact", "resize", "crop", "cover"}, "exact"));
  const std::int64_t max_pixels = max_pixels_option(a);
  const auto share = dist::share_size(clips.size(), job.group->rank(), job.group->size());
  Progress bar(con, "generate", static_cast<std::int64_t>(share), "clip");
  return share_message_in_batches(*job.group, clips.size(), static_cast<std::size_t>(batch),
                                  [&](const std::vector<std::size_t>& indices, const ItemWriter& item) {
    std::vector<Clip> inputs;  // read before any ClipGeneration holds a reference into them
    for (const std::size_t i : indices)  // listed, read and checked by generation_clips
      inputs.push_back(window_clip(clips[i].frames, clips[i].poses, wc.condition_frames, wc.image_h, wc.image_w, policy,
                                   max_pixels));
    std::vector<std::unique_ptr<ClipGeneration>> generations;
    std::vector<RolloutItem> items;
    for (std::size_t k = 0; k < indices.size(); ++k) {
      const std::filesystem::path dir = out / clips[indices[k]].name;
      prepare_output_dir(dir, "--out " + dir.string());
      RolloutPlan own = plan;
      own.seed = base.seed + indices[k];
      generations.push_back(std::make_unique<ClipGeneration>(*engine, ctx, inputs[k], own, dir, wc, std::nullopt, silent));
      items.push_back(generations.back()->item());
    }
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<RolloutLog> logs = roll_out_batch(*engine, ctx, std::move(items), wc, plan, silent);
    const double seconds = seconds_since(t0);
    for (std::size_t k = 0; k < indices.size(); ++k) {
      const GeneratedClip g = generations[k]->finish(ctx, logs[k], wc, seconds);
      const std::filesystem::path dir = out / clips[indices[k]].name;
      const std::string together = indices.size() > 1 ? " (a batch of " + std::to_string(indices.size()) + " clips)" : "";
      item(indices[k]).put(dir.string() + ": " + counted(plan.frames, "frame") + " in " + duration_text(g.seconds) +
                           together + ", seed " + std::to_string(base.seed + indices[k]));
      bar.advance();
    }
  });
}

inline int run_generate_clips(const ParsedArgs& a, const Console& console) {
  for (const char* single : {"frames", "poses", "video"})
    if (a.has(single)) usage_fail("--clips and --", single, " do not go together (--", single, " is for one clip)");
  const ComputeOptions compute = compute_options(a);
  const Job job = join_job(console, compute);
  const Console& con = job.con;
  const ModelFiles files = resolve_models(a, true, true);
  const WorldModelConfig& wc = files.configs.world;
  const RolloutPlan plan = rollout_plan(a, wc);
  const std::int64_t batch = batch_option(a);
  const std::vector<eval::EvalClip> clips = generation_clips(a, wc);
  const auto out = output_dir(a, "out/generate");
  note_rollout(con, a, plan, " for each of " + counted(std::int64_t(clips.size()), "clip") + " (clip i: seed + i)" +
                                 batch_note(batch) + job.split_note());
  const std::vector<std::string> by_rank =
      run_on_every_rank(*job.group, [&] { return generate_share(a, clips, plan, batch, files, compute, out, job); });
  if (!job.group->is_root()) return 0;  // rank 0 reports, and fails for every rank
  const auto get_line = [](dist::MessageReader& m) { return m.get_string(); };
  for (const auto& line : items_in_order<std::string>(by_rank, clips.size(), get_line)) con.out << "wrote " << line << "\n";
  con.out << "generated " << counted(plan.frames, "frame") << " for each of " << counted(std::int64_t(clips.size()), "clip")
          << " into " << out.string() << "/<clip>/\n";
  return 0;
}

// ---- one clip -------------------------------------------------------------------------------

inline int run_generate(const ParsedArgs& a, const Console& con) {
  if (a.has("clips")) return run_generate_clips(a, con);
  check_launch(dist::launch_from_environment(), "generate of one clip");
  if (a.has("batch")) usage_fail("--batch is for --clips (it rolls several clips out together); one clip has nothing to batch");
  const ComputeOptions compute = compute_options(a);
  const ModelFiles files = resolve_models(a, true, true);
  const WorldModelConfig& wc = files.configs.world;
  RolloutPlan plan = rollout_plan(a, wc);
  const std::optional<VideoRequest> video_to = video_request(a);
  const Clip clip = load_clip_for(a, files, con);
  const auto dir = output_dir(a, "out/generate");

  const auto engine = make_engine(compute);
  cpu::Context ctx(compute.threads);
  engine->load_dcae(files, con);
  engine->load_world(files, con);
  plan.clip_len = decode_clip_length(a, engine->dcae_config());
  note_rollout(con, a, plan, "");
  const GeneratedClip g = generate_into(*engine, ctx, clip, plan, dir, wc, video_to, con);
  print_generate_summary(con.out, dir, wc, plan.frames, g.seconds, g.sheet, g.inputs, g.shown, plan.actions.has_value(),
                         plan.keep_latents, g.video_line);
  return 0;
}

}  // namespace epona::app
