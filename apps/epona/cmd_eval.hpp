// apps/epona/cmd_eval.hpp — `epona eval`: scores the world model on a clip set (as `epona synth`
// writes it) the way the Epona paper evaluates: open-loop planning (L2 at 1/2/3 s, collision
// rate) against constant-velocity and constant-turn baselines, and video quality (PSNR, SSIM per
// horizon) of rollouts driven by the true future motions, beside the repeat-last-frame baseline
// and the DC-AE's own reconstruction (the ceiling). With --control, trajectory control: the same
// window rolled out under "turn left" and "turn right", scored by the horizontal shift between the
// two frames (include/epona/eval/control_metrics.hpp). One JSON report, written atomically.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numeric>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "args.hpp"
#include "cmd_common.hpp"
#include "console.hpp"
#include "engine.hpp"
#include "frames.hpp"
#include "models.hpp"
#include "rollout_common.hpp"
#include "epona/eval/baselines.hpp"
#include "epona/eval/clip_set.hpp"
#include "epona/eval/control_metrics.hpp"
#include "epona/eval/feature_metrics.hpp"
#include "epona/eval/ground_truth.hpp"
#include "epona/eval/image_metrics.hpp"
#include "epona/eval/planning_metrics.hpp"
#include "epona/io/atomic_file.hpp"
#include "processes.hpp"

namespace epona::app {

inline ArgParser eval_parser() {
  ArgParser p("epona eval", "--clips DIR --json FILE [options]",
              "Evaluates the world model on a clip set (DIR/clip_*/ with frames/, poses.csv, future/,\n"
              "future_poses.csv, boxes.json, as `epona synth` writes): plans from each clip's last F frames\n"
              "(L2 at 1/2/3 s, collision rate) beside constant-velocity and constant-turn baselines, and rolls\n"
              "out --horizon frames under the true future motions (PSNR, SSIM per horizon) beside repeating\n"
              "the last frame and the DC-AE's reconstruction of the true frames. --control also rolls each window\n"
              "out under \"turn left\" and \"turn right\" and checks that the road shifts the matching way. DIR may\n"
              "also be one clip folder. Writes one JSON report and prints a table. Without --weights it runs the\n"
              "bundled demo model.");
  add_model_options(p, true, true);
  p.option("clips", "DIR", "the clip set (every subfolder holding frames/, in natural name order)")
      .option("json", "FILE", "the report to write (atomically)")
      .option("horizon", "N", "video horizons 1..N scored", "5")
      .option("limit", "N", "evaluate only the first N clips", "all")
      .flag("no-video", "skip the video metrics (no rollouts)")
      .flag("no-plan", "skip the planning metrics")
      .flag("control", "score trajectory control: turn left vs turn right from each clip's window")
      .option("control-yaw", "DEG", "the turns' yaw per frame, degrees (1..7)", "5")
      .option("control-frames", "N", "frames rolled out per turn; the last one is compared", "1")
      .option("fit", "MODE", "frames not at the model's size: exact (refuse), resize, crop, cover", "exact")
      .option("save-frames", "DIR", "also write each clip's generated video frames to DIR/<clip>/frame_NNNN.png "
              "(to compare samplers with each other, scripts/solver_sweep.sh)", "none");
  add_sampling_options(p);
  add_hypothesis_options(p);
  add_batch_option(p);
  add_compute_options(p);
  p.flag("quiet", "no progress bars or notes on stderr", 'q');
  p.epilog("examples:\n"
           "  epona synth --out clips/ && epona eval --clips clips/ --json eval.json   # the bundled demo model\n"
           "  epona eval --weights world.pkl --dcae dcae_td_20000.pkl --clips clips/ --json eval.json \\\n"
           "             --steps 100 --backend cuda\n"
           "  epona eval --clips clips/ --json fast.json --solver dpmpp2m --plan-steps 10 --video-steps 15\n"
           "  epona eval --clips clips/ --json k8.json --no-video --hypotheses 8 --choose mean   # the chosen plan and "
           "the best of 8");
  return p;
}

struct EvalOptions {
  std::filesystem::path clips, json;
  std::int64_t horizon = 5;
  std::optional<std::int64_t> limit;
  bool plan = true, video = true, control = false;
  std::int64_t control_yaw = 5, control_frames = 1;
  std::string fit = "exact";
  SampleOptions sample;
  DitSamplers samplers;                       // what sample resolves to, per DiT
  HypothesisOptions planning;  // hypotheses per scene and the rule that picks one
  std::int64_t batch = 1;      // clips run together (--batch)
  std::optional<std::filesystem::path> save_frames;
};

inline EvalOptions eval_options(const ParsedArgs& a, const io::ModelConfigs& configs) {
  const WorldModelConfig& wc = configs.world;
  EvalOptions o;
  if (!a.has("clips")) usage_fail("eval: --clips DIR is needed (the clip set to evaluate)");
  if (!a.has("json")) usage_fail("eval: --json FILE is needed (where the report goes)");
  o.clips = *a.get("clips");
  o.json = *a.get("json");
  o.horizon = a.integer("horizon", 5, 1, 1000);
  o.limit = a.maybe_integer("limit", 1);
  o.plan = !a.flag("no-plan"), o.video = !a.flag("no-video"), o.control = a.flag("control");
  if (!o.plan && !o.video && !o.control) usage_fail("eval: --no-plan and --no-video leave nothing to evaluate");
  // |yaw| < 8: inside the pose tokenizer's range (yaw_range 16 degrees, centred).
  o.control_yaw = a.integer("control-yaw", 5, 1, 7);
  o.control_frames = a.integer("control-frames", 1, 1, 100);
  o.fit = a.choice("fit", {"exact", "resize", "crop", "cover"}, "exact");
  o.sample = sample_options(a, wc);
  o.samplers = samplers_of(o.sample);
  o.planning = hypothesis_options(a, configs.planner);
  o.batch = batch_option(a);
  if (const auto dir = a.get("save-frames")) o.save_frames = *dir;
  std::error_code ec;
  const auto parent = std::filesystem::absolute(o.json, ec).parent_path();
  EPONA_CHECK(std::filesystem::is_directory(parent, ec), "--json ", o.json.string(), ": the folder ", parent.string(),
              " does not exist");
  output_detail::check_writable(parent, "--json " + o.json.string());  // before the clips are scored
  return o;
}

// ---- per clip -------------------------------------------------------------------------------

// A planner's scores on one clip.
struct PlanScores {
  eval::L2Errors l2;
  eval::Collisions collisions;  // all none without boxes.json
};

// Trajectory control on one clip: the shift of the left-turn frame against the right-turn frame
// (eval::horizontal_shift; > 0 when the road moved the way the turns say).
struct ControlScore {
  double forward_m = 0;  // the forward motion of both turns, per frame
  eval::ShiftEstimate shift;
  bool agrees() const { return shift.shift > 0; }
};

struct ClipScores {
  std::string name;
  std::optional<PlanScores> model, constant_velocity, constant_turn, ground_truth;
  std::optional<PlanScores> best_of_k;  // per horizon the least error of the K hypotheses (no collisions)
  std::vector<double> spread_m;         // per waypoint, of the K hypotheses; empty with one
  std::vector<double> psnr, ssim, repeat_psnr, repeat_ssim, ae_psnr, ae_ssim;  // per horizon; empty: no video
  std::optional<ControlScore> control;
  Tensor<float> plan;  // (traj_len, 3) the model's plan; empty without planning
};

// ---- a clip's scores as a message (from the rank that scored it to rank 0) -----------------

inline void put_plan(dist::MessageWriter& m, const std::optional<PlanScores>& p) {
  m.put(std::uint8_t(p.has_value()));
  if (!p) return;
  for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) {
    m.put(p->l2.at[k]).put(p->l2.avg[k]);
    m.put(std::int8_t(p->collisions[k] ? int(*p->collisions[k]) : -1));
  }
}

inline std::optional<PlanScores> get_plan(dist::MessageReader& m) {
  if (!m.get<std::uint8_t>()) return std::nullopt;
  PlanScores p;
  for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) {
    p.l2.at[k] = m.get<double>(), p.l2.avg[k] = m.get<double>();
    const auto hit = m.get<std::int8_t>();
    if (hit >= 0) p.collisions[k] = hit != 0;
  }
  return p;
}

inline void put_scores(dist::MessageWriter& m, const ClipScores& s) {
  m.put(s.name);
  for (const auto* p : {&s.model, &s.constant_velocity, &s.constant_turn, &s.ground_truth, &s.best_of_k}) put_plan(m, *p);
  m.put(s.spread_m);
  for (const auto* v : {&s.psnr, &s.ssim, &s.repeat_psnr, &s.repeat_ssim, &s.ae_psnr, &s.ae_ssim}) m.put(*v);
  m.put(std::uint8_t(s.control.has_value()));
  if (s.control) m.put(s.control->forward_m).put(s.control->shift.shift).put(s.control->shift.mad).put(s.control->shift.mad_at_zero);
  m.put(std::vector<std::int64_t>(s.plan.shape().begin(), s.plan.shape().end()));
  m.put(std::vector<float>(s.plan.data(), s.plan.data() + s.plan.numel()));
}

inline ClipScores get_scores(dist::MessageReader& m) {
  ClipScores s;
  s.name = m.get_string();
  for (auto* p : {&s.model, &s.constant_velocity, &s.constant_turn, &s.ground_truth, &s.best_of_k}) *p = get_plan(m);
  s.spread_m = m.get_vector<double>();
  for (auto* v : {&s.psnr, &s.ssim, &s.repeat_psnr, &s.repeat_ssim, &s.ae_psnr, &s.ae_ssim}) *v = m.get_vector<double>();
  if (m.get<std::uint8_t>()) {
    ControlScore c;
    c.forward_m = m.get<double>();
    c.shift.shift = m.get<std::int64_t>(), c.shift.mad = m.get<double>(), c.shift.mad_at_zero = m.get<double>();
    s.control = c;
  }
  const auto shape = m.get_vector<std::int64_t>();
  const auto values = m.get_vector<float>();
  if (!shape.empty()) {
    s.plan = Tensor<float>(Shape(shape.begin(), shape.end()));
    EPONA_CHECK(std::size_t(s.plan.numel()) == values.size(), "a clip's plan from another rank has ", values.size(),
                " values for its shape");
    std::copy(values.begin(), values.end(), s.plan.data());
  }
  return s;
}

inline PlanScores score_plan(const std::vector<eval::Pose2>& plan, const std::vector<eval::Pose2>& truth,
                             const eval::EvalClip& c) {
  PlanScores s{eval::l2_errors(plan, truth), {}};
  if (c.boxes) s.collisions = eval::plan_collisions(plan, c.boxes->ego, c.future_boxes());
  return s;
}

// Keeps decoded frames in memory.
class FrameCollector final : public FrameConsumer {
 public:
  void put(const io::Image& img) override { frames.push_back(img); }
  std::vector<io::Image> frames;
};

// Everything a clip's evaluation uses, loaded once.
struct EvalContext {
  Engine& engine;
  cpu::Context& ctx;
  const WorldModelConfig& wc;
  const EvalOptions& opt;
  io::SizePolicy fit;
  const Console& silent;  // for the per-clip rollout (the progress bar is over clips)
};

inline std::vector<io::Image> read_frames(const std::vector<std::filesystem::path>& files, std::size_t first,
                                          std::size_t count, const EvalContext& e) {
  std::vector<io::Image> out;
  for (std::size_t i = first; i < first + count; ++i) out.push_back(read_frame(files[i], e.wc.image_h, e.wc.image_w, e.fit));
  return out;
}

// The least L2 error of the hypotheses (K, W, 3), at and up to each horizon separately (minFDE and
// minADE style); collisions are not scored.
inline PlanScores best_of(const Tensor<float>& plans, const std::vector<eval::Pose2>& truth) {
  PlanScores best{eval::l2_errors(eval::poses_of(plans[0]), truth), {}};
  for (std::int64_t k = 1; k < plans.size(0); ++k) {
    const eval::L2Errors e = eval::l2_errors(eval::poses_of(plans[k]), truth);
    for (std::size_t t = 0; t < eval::kPlanSeconds; ++t)
      best.l2.at[t] = std::min(best.l2.at[t], e.at[t]), best.l2.avg[t] = std::min(best.l2.avg[t], e.avg[t]);
  }
  return best;
}

// Scores the model's plans of one clip (K, W, 3) and the baselines.
inline void score_plans(ClipScores& s, const eval::EvalClip& c, const Tensor<float>& plans, const EvalContext& e) {
  const auto truth = eval::cumulative_poses(*c.future_motions, eval::kPlanWaypoints);
  const model::PlanFan fan = model::choose_plan(plans, e.opt.planning.choose);
  s.plan = fan.chosen;
  s.model = score_plan(eval::poses_of(fan.chosen), truth, c);
  if (plans.size(0) > 1) s.best_of_k = best_of(plans, truth), s.spread_m = fan.spread_m;
  const eval::Pose2 last = eval::motion_at(c.poses, c.poses.size() - 1);
  s.constant_velocity = score_plan(eval::constant_velocity(last, eval::kPlanWaypoints), truth, c);
  s.constant_turn = score_plan(eval::constant_turn(last, eval::kPlanWaypoints), truth, c);
  s.ground_truth = score_plan(truth, truth, c);
}

// The plans (K, W, 3) of each window (batch 1), window b with seeds[b]. One plan each: one
// planner call over the batch, each window's noise its own (per-item seeds). K hypotheses: one
// plan_hypotheses call per window, hypothesis k with seeds[b] + k*0x9E3779B9, as alone.
inline std::vector<Tensor<float>> plans_of(const std::vector<const History*>& windows,
                                           const std::vector<std::uint64_t>& seeds, const EvalContext& e) {
  const std::int64_t K = e.opt.planning.hypotheses;
  std::vector<Tensor<float>> out;
  SampleOptions o = e.opt.sample;
  if (K > 1) {
    for (std::size_t b = 0; b < windows.size(); ++b) {
      o.seed = seeds[b];
      out.push_back(e.engine.plan_hypotheses(*windows[b], K, o));
    }
    return out;
  }
  o.item_seeds = seeds;
  const Tensor<float> plans = e.engine.plan(stack_windows(windows), o);  // (Bt, W, 3)
  for (std::int64_t b = 0; b < plans.size(0); ++b) out.push_back(plans.slice(b, b + 1).clone());
  return out;
}

// Each window (batch 1) rolled out under its actions (one per frame, as many for every window),
// window b with seeds[b], all in one batched rollout; each latent decoded alone (frame mode).
inline std::vector<std::vector<io::Image>> roll_out_under(const std::vector<const History*>& windows,
                                                          std::vector<io::PoseSequence> actions,
                                                          const std::vector<std::uint64_t>& seeds, const EvalContext& e) {
  RolloutPlan plan;
  plan.frames = static_cast<std::int64_t>(actions.front().size()), plan.samplers = e.opt.samplers, plan.clip_len = 1;
  std::vector<FrameCollector> out(windows.size());
  std::vector<RolloutItem> items;
  for (std::size_t b = 0; b < windows.size(); ++b) items.push_back({*windows[b], seeds[b], std::move(actions[b]), &out[b]});
  roll_out_batch(e.engine, e.ctx, std::move(items), e.wc, plan, e.silent);
  std::vector<std::vector<io::Image>> frames;
  for (auto& collected : out) frames.push_back(std::move(collected.frames));
  return frames;
}

// frame_0000.png ... of a clip's generated frames, in `dir` (created).
inline void save_frames(const std::filesystem::path& dir, const std::vector<io::Image>& frames) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  EPONA_CHECK(std::filesystem::is_directory(dir, ec), "--save-frames: cannot create ", dir.string());
  for (std::size_t h = 0; h < frames.size(); ++h) {
    char name[32];
    std::snprintf(name, sizeof name, "frame_%04zu.png", h);
    io::write_png((dir / name).string(), frames[h]);
  }
}

// The video scores of a clip's generated frames (one per horizon) against its true future frames,
// beside repeating the last history frame and the DC-AE's reconstruction.
inline void score_video(ClipScores& s, const eval::EvalClip& c, const std::vector<io::Image>& history,
                        const std::vector<io::Image>& generated, const EvalContext& e) {
  const auto N = static_cast<std::size_t>(e.opt.horizon);
  const std::vector<io::Image> truth = read_frames(c.future_frames, 0, N, e);
  if (e.opt.save_frames) save_frames(*e.opt.save_frames / c.name, generated);
  const io::Image& last = eval::repeat_last_frame(history);
  for (std::size_t h = 0; h < N; ++h) {
    s.psnr.push_back(eval::psnr(generated[h], truth[h]));
    s.ssim.push_back(eval::ssim(generated[h], truth[h]));
    s.repeat_psnr.push_back(eval::psnr(last, truth[h]));
    s.repeat_ssim.push_back(eval::ssim(last, truth[h]));
    const io::Image recon = io::tensor_to_image(e.engine.decode(e.engine.encode(truth[h]), false), 0);
    s.ae_psnr.push_back(eval::psnr(recon, truth[h]));
    s.ae_ssim.push_back(eval::ssim(recon, truth[h]));
  }
}

// A turn needs some speed to read as one: the turns go at least this far forward per frame.
inline constexpr double kControlMinForward = 2.0;  // metres

// `frames` steps of (forward, 0, yaw): a steady turn at the clip's speed.
inline io::PoseSequence steady_turn(double forward, double yaw_deg, std::int64_t frames) {
  io::PoseSequence p;
  for (std::int64_t i = 0; i < frames; ++i)
    p.x.push_back(float(forward)), p.y.push_back(0.0f), p.yaw.push_back(float(yaw_deg));
  return p;
}

// The forward motion of a clip's turns: its last history motion's, at least kControlMinForward.
inline double control_forward(const eval::EvalClip& c) { return std::max(double(c.poses.x.back()), kControlMinForward); }

// Each window and its noise rolled out turning left (+yaw) and turning right (-yaw), the left
// turns of the batch in one rollout and the right turns in another; the last frames compared below
// the horizon (the lower half: road, markings, kerbs).
inline void score_control(std::vector<ClipScores>& scores, const std::vector<const eval::EvalClip*>& clips,
                          const std::vector<const History*>& windows, const std::vector<std::uint64_t>& seeds,
                          const EvalContext& e) {
  const double yaw = double(e.opt.control_yaw);
  const auto turns = [&](double sign) {
    std::vector<io::PoseSequence> actions;
    for (const auto* c : clips) actions.push_back(steady_turn(control_forward(*c), sign * yaw, e.opt.control_frames));
    return roll_out_under(windows, std::move(actions), seeds, e);
  };
  const auto left = turns(+1.0), right = turns(-1.0);
  for (std::size_t k = 0; k < clips.size(); ++k)
    scores[k].control = ControlScore{control_forward(*clips[k]), eval::horizontal_shift(left[k].back(), right[k].back())};
}

// A clip's window and the history frames it encodes, read once for all its scores.
struct ClipInput {
  std::vector<io::Image> history;
  History window;
};

inline ClipInput read_input(const eval::EvalClip& c, const EvalContext& e) {
  const auto F = static_cast<std::size_t>(e.wc.condition_frames);
  ClipInput in{read_frames(c.frames, c.frames.size() - F, F, e), {}};
  const io::PoseSequence poses = c.poses.slice(c.poses.size() - F, F);
  in.window = model::make_window(e.ctx, encode_frames(e.engine, in.history, e.silent), poses);
  return in;
}

// The clips of a batch that `wanted` selects, as positions in the batch.
template <class Wanted>
std::vector<std::size_t> members(const std::vector<const eval::EvalClip*>& clips, Wanted&& wanted) {
  std::vector<std::size_t> out;
  for (std::size_t k = 0; k < clips.size(); ++k)
    if (wanted(*clips[k])) out.push_back(k);
  return out;
}

// Scores a batch of clips, clip k with seeds[k] (for its plan, its rollout and both control
// rollouts). Work of the same shape over the clips runs as one batched call: the plans (one
// each), the video rollouts, the left turns and the right turns. Each clip's noise is its own
// (per-item seeds), so its scores are those of a batch of one up to rounding.
inline std::vector<ClipScores> evaluate_batch(const std::vector<const eval::EvalClip*>& clips,
                                              const std::vector<std::uint64_t>& seeds, const EvalContext& e) {
  std::vector<ClipScores> scores(clips.size());
  std::vector<ClipInput> inputs;
  for (std::size_t k = 0; k < clips.size(); ++k) scores[k].name = clips[k]->name, inputs.push_back(read_input(*clips[k], e));
  const auto windows_of = [&](const std::vector<std::size_t>& ks) {
    std::vector<const History*> w;
    for (const std::size_t k : ks) w.push_back(&inputs[k].window);
    return w;
  };
  const auto seeds_of = [&](const std::vector<std::size_t>& ks) {
    std::vector<std::uint64_t> out;
    for (const std::size_t k : ks) out.push_back(seeds[k]);
    return out;
  };
  const auto planned = members(clips, [&](const eval::EvalClip& c) { return e.opt.plan && c.future_motions.has_value(); });
  if (!planned.empty()) {
    const auto plans = plans_of(windows_of(planned), seeds_of(planned), e);
    for (std::size_t m = 0; m < planned.size(); ++m) score_plans(scores[planned[m]], *clips[planned[m]], plans[m], e);
  }
  const auto filmed = members(clips, [&](const eval::EvalClip& c) { return e.opt.video && !c.future_frames.empty(); });
  if (!filmed.empty()) {
    std::vector<io::PoseSequence> actions;
    for (const std::size_t k : filmed) actions.push_back(clips[k]->future_motions->slice(0, std::size_t(e.opt.horizon)));
    const auto generated = roll_out_under(windows_of(filmed), std::move(actions), seeds_of(filmed), e);
    for (std::size_t m = 0; m < filmed.size(); ++m)
      score_video(scores[filmed[m]], *clips[filmed[m]], inputs[filmed[m]].history, generated[m], e);
  }
  if (e.opt.control) {
    std::vector<std::size_t> every(clips.size());
    std::iota(every.begin(), every.end(), std::size_t{0});
    score_control(scores, clips, windows_of(every), seeds, e);
  }
  return scores;
}

// ---- over the clips -------------------------------------------------------------------------

// The mean over the clips that have a value; none when no clip has one.
struct Mean {
  double sum = 0;
  std::int64_t count = 0;
  void add(double v) { sum += v, ++count; }
  std::optional<double> value() const { return count ? std::optional(sum / double(count)) : std::nullopt; }
};

inline nlohmann::ordered_json number(std::optional<double> v) {
  return v && std::isfinite(*v) ? nlohmann::ordered_json(*v) : nlohmann::ordered_json(nullptr);
}

// Mean L2s and collision rates of one planner over the clips.
inline nlohmann::ordered_json plan_summary(const std::vector<ClipScores>& clips,
                                           std::optional<PlanScores> ClipScores::*planner) {
  std::array<Mean, eval::kPlanSeconds> at, avg, hit;
  for (const auto& c : clips) {
    if (!(c.*planner)) continue;
    const PlanScores& p = *(c.*planner);
    for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) {
      at[k].add(p.l2.at[k]), avg[k].add(p.l2.avg[k]);
      if (p.collisions[k]) hit[k].add(*p.collisions[k] ? 1.0 : 0.0);
    }
  }
  nlohmann::ordered_json j;
  for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) j["l2_" + std::to_string(k + 1) + "s"] = number(at[k].value());
  for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) j["l2_avg_" + std::to_string(k + 1) + "s"] = number(avg[k].value());
  j["collision_rate"] = number(hit[eval::kPlanSeconds - 1].value());  // any waypoint up to 3 s
  for (std::size_t k = 0; k < eval::kPlanSeconds; ++k)
    j["collision_rate_" + std::to_string(k + 1) + "s"] = number(hit[k].value());
  j["clips"] = at[0].count;
  j["collision_clips"] = hit[eval::kPlanSeconds - 1].count;
  return j;
}

// Mean of a per-horizon series over the clips that have it.
inline nlohmann::ordered_json series_mean(const std::vector<ClipScores>& clips, std::vector<double> ClipScores::*series,
                                          std::int64_t horizon) {
  std::vector<Mean> m(static_cast<std::size_t>(horizon));
  for (const auto& c : clips)
    for (std::size_t h = 0; h < (c.*series).size() && h < m.size(); ++h) m[h].add((c.*series)[h]);
  auto j = nlohmann::ordered_json::array();
  for (const auto& v : m) j.push_back(number(v.value()));
  return j;
}

inline nlohmann::ordered_json video_summary(const std::vector<ClipScores>& clips, std::vector<double> ClipScores::*psnr,
                                            std::vector<double> ClipScores::*ssim, std::int64_t horizon) {
  return {{"psnr", series_mean(clips, psnr, horizon)}, {"ssim", series_mean(clips, ssim, horizon)}};
}

inline nlohmann::ordered_json numbers(const std::vector<double>& v) {
  auto j = nlohmann::ordered_json::array();
  for (double x : v) j.push_back(number(x));
  return j;
}

// The share of clips whose turns shifted the road the matching way, and the shifts.
inline nlohmann::ordered_json control_summary(const std::vector<ClipScores>& clips, const EvalOptions& o) {
  std::vector<std::int64_t> shifts;
  std::int64_t agree = 0;
  for (const auto& c : clips)
    if (c.control) shifts.push_back(c.control->shift.shift), agree += c.control->agrees() ? 1 : 0;
  nlohmann::ordered_json j;
  j["scenes"] = shifts.size();
  j["agree"] = agree;
  j["agree_rate"] = shifts.empty() ? nlohmann::ordered_json(nullptr) : nlohmann::ordered_json(double(agree) / double(shifts.size()));
  j["yaw_deg"] = o.control_yaw;
  j["frames"] = o.control_frames;
  j["min_forward_m"] = kControlMinForward;
  std::vector<std::int64_t> sorted = shifts;
  std::sort(sorted.begin(), sorted.end());
  j["shift_min_px"] = sorted.empty() ? nlohmann::ordered_json(nullptr) : nlohmann::ordered_json(sorted.front());
  j["shift_median_px"] = sorted.empty() ? nlohmann::ordered_json(nullptr) : nlohmann::ordered_json(sorted[sorted.size() / 2]);
  j["shift_max_px"] = sorted.empty() ? nlohmann::ordered_json(nullptr) : nlohmann::ordered_json(sorted.back());
  j["per_clip"] = shifts;
  return j;
}

inline nlohmann::ordered_json clip_json(const ClipScores& c) {
  nlohmann::ordered_json j;
  j["name"] = c.name;
  const auto plan = [&](const char* prefix, const std::optional<PlanScores>& p) {
    for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) {
      const std::string t = std::to_string(k + 1) + "s";
      j[prefix + ("l2_" + t)] = p ? number(p->l2.at[k]) : nullptr;
      j[prefix + ("l2_avg_" + t)] = p ? number(p->l2.avg[k]) : nullptr;
      j[prefix + ("collision_" + t)] = p && p->collisions[k] ? nlohmann::ordered_json(*p->collisions[k]) : nullptr;
    }
  };
  plan("", c.model);
  plan("constant_velocity_", c.constant_velocity);
  plan("constant_turn_", c.constant_turn);
  if (c.best_of_k) plan("best_of_k_", c.best_of_k), j["spread_m"] = numbers(c.spread_m);
  j["psnr"] = numbers(c.psnr), j["ssim"] = numbers(c.ssim);
  j["repeat_last_psnr"] = numbers(c.repeat_psnr), j["repeat_last_ssim"] = numbers(c.repeat_ssim);
  j["autoencoder_psnr"] = numbers(c.ae_psnr), j["autoencoder_ssim"] = numbers(c.ae_ssim);
  j["control_shift_px"] = c.control ? nlohmann::ordered_json(c.control->shift.shift) : nullptr;
  auto waypoints = nlohmann::ordered_json::array();  // the planned waypoints, to compare samplers
  for (std::int64_t w = 0; w < c.plan.numel() / 3; ++w)
    waypoints.push_back({c.plan.data()[3 * w], c.plan.data()[3 * w + 1], c.plan.data()[3 * w + 2]});
  j["trajectory"] = c.plan.empty() ? nlohmann::ordered_json(nullptr) : waypoints;
  return j;
}

inline nlohmann::ordered_json settings_json(const ParsedArgs& a, const ModelFiles& f, const ComputeOptions& c,
                                            const EvalOptions& o, const WorldModelConfig& wc) {
  const auto sampler = [](const flow::SolverSetting& s) {
    return nlohmann::ordered_json{{"solver", flow::solver_name(s.kind)}, {"steps", s.steps}, {"evaluations", s.evaluations()}};
  };
  return {{"steps", *o.sample.steps},
          {"sampler", a.text("sampler", "official")},
          {"solver", flow::solver_name(o.sample.solver)},
          {"plan_sampler", sampler(o.samplers.plan)},
          {"video_sampler", sampler(o.samplers.video)},
          {"seed", o.sample.seed},
          {"seed_rule", "clip i (0-based, in clip order) uses seed + i, for its plan, its rollout and both control rollouts; "
                        "with hypotheses, hypothesis k of clip i uses seed + i + k*0x9E3779B9 (the generator keeps the low 32 bits)"},
          {"hypotheses", o.planning.hypotheses},
          {"batch", o.batch},
          {"choose", model::plan_choice_name(o.planning.choose)},
          {"planning_rule_from", o.planning.from_model ? "the model's configs.json (planner)" : "the command line or the default"},
          {"horizon", o.horizon},
          {"limit", o.limit ? nlohmann::ordered_json(*o.limit) : nullptr},
          {"plan", o.plan},
          {"video", o.video},
          {"control", o.control},
          {"control_yaw_deg", o.control_yaw},
          {"control_frames", o.control_frames},
          {"clips_dir", o.clips.string()},
          {"weights", f.demo ? "bundled demo model (" + f.world + ")" : f.world},
          {"dcae", f.dcae},
          {"config", f.config_source},
          {"backend", c.backend},
          {"dtype", c.bf16_weights ? "bfloat16" : "float32"},
          {"threads", a.text("threads", "all")},
          {"fit", o.fit},
          {"condition_frames", wc.condition_frames},
          {"image_size", {wc.image_h, wc.image_w}}};
}

inline nlohmann::ordered_json notes_json() {
  nlohmann::ordered_json j;
  j["l2"] = "l2_Ns: Euclidean distance between planned and true waypoint at N s (index 5N-1 at 5 Hz; UniAD's "
            "at-time convention); l2_avg_Ns: mean over the waypoints up to N s (ST-P3/VAD convention); metres";
  j["collision"] = "ego box (boxes.json ego size, heading = waypoint yaw, centred on the waypoint) against the other "
                   "vehicles' boxes of the matching future frame, separating-axis test, touching counts; "
                   "collision_rate_Ns: fraction of clips with boxes whose plan collides at any waypoint up to N s; "
                   "collision_rate = collision_rate_3s";
  j["hypotheses"] = "with --hypotheses K (or the model's configs.json \"planner\" rule): `model` scores the plan --choose picks of the K (model/plan_choice.hpp); "
                    "model_best_of_k: per clip and horizon the least L2 of the K (minFDE at N s, minADE up to N s), "
                    "no collisions; spread_Ns: RMS distance of the K waypoint positions at N s from their mean";
  j["psnr"] = "8-bit RGB, MAX 255, MSE over all pixels and channels; identical frames reported as " +
              std::to_string(int(eval::kPsnrCap)) + " dB";
  j["ssim"] = "Wang et al. 2004: 11x11 Gaussian window sigma 1.5, K1 0.01, K2 0.03, L 255, valid positions, mean "
              "over the RGB channels";
  j["video"] = "rollout driven by the true future motions (future_poses.csv), each latent decoded alone (frame mode)";
  j["control"] = "the window rolled out `frames` frames turning left (x = the last history motion's forward "
                 "distance, at least min_forward_m; y = 0; yaw = +yaw_deg per frame) and turning right (yaw = "
                 "-yaw_deg), same noise; shift = the integer column offset in [-W/4, W/4] minimising the mean "
                 "absolute grey difference of the two last frames' lower halves, > 0 when the left-turn frame's "
                 "content lies right of the right-turn frame's, which is the matching way (turning left moves "
                 "the scene right in the image); agree: shift > 0; per_clip: the shifts in pixels";
  for (const auto& m : eval::uncomputed_feature_metrics()) j[m.name] = m.note;
  return j;
}

// K, the rule, and the mean spread of the hypotheses at 1, 2 and 3 s.
inline nlohmann::ordered_json hypotheses_summary(const std::vector<ClipScores>& clips, const EvalOptions& o) {
  nlohmann::ordered_json j{{"count", o.planning.hypotheses}, {"choose", model::plan_choice_name(o.planning.choose)}};
  for (std::size_t k = 0; k < eval::kPlanSeconds; ++k) {
    Mean m;
    for (const auto& c : clips)
      if (c.spread_m.size() >= eval::kPlanWaypoints) m.add(c.spread_m[eval::waypoint_at(k + 1)]);
    j["spread_" + std::to_string(k + 1) + "s"] = number(m.value());
  }
  return j;
}

inline nlohmann::ordered_json report_json(const std::vector<ClipScores>& clips, const nlohmann::ordered_json& settings,
                                          const EvalOptions& o) {
  const std::int64_t horizon = o.horizon;
  const bool video = o.video;
  nlohmann::ordered_json j;
  j["clips"] = clips.size();
  auto model = plan_summary(clips, &ClipScores::model);
  if (video) model.update(video_summary(clips, &ClipScores::psnr, &ClipScores::ssim, horizon));
  for (const auto& m : eval::uncomputed_feature_metrics()) model[m.name] = number(m.value);
  j["model"] = model;
  if (o.planning.hypotheses > 1) {
    j["model_best_of_k"] = plan_summary(clips, &ClipScores::best_of_k);
    j["hypotheses"] = hypotheses_summary(clips, o);
  }
  j["constant_velocity"] = plan_summary(clips, &ClipScores::constant_velocity);
  j["constant_turn"] = plan_summary(clips, &ClipScores::constant_turn);
  j["ground_truth"] = plan_summary(clips, &ClipScores::ground_truth);
  if (video) {
    j["repeat_last"] = video_summary(clips, &ClipScores::repeat_psnr, &ClipScores::repeat_ssim, horizon);
    j["autoencoder"] = video_summary(clips, &ClipScores::ae_psnr, &ClipScores::ae_ssim, horizon);
  }
  if (o.control) j["control"] = control_summary(clips, o);
  for (const auto& m : eval::uncomputed_feature_metrics()) j[m.name] = number(m.value);
  j["settings"] = settings;
  j["notes"] = notes_json();
  j["per_clip"] = nlohmann::ordered_json::array();
  for (const auto& c : clips) j["per_clip"].push_back(clip_json(c));
  return j;
}

// ---- the table ------------------------------------------------------------------------------

inline std::string cell(const nlohmann::ordered_json& v, const char* format) {
  if (!v.is_number()) return "-";
  char buf[32];
  std::snprintf(buf, sizeof buf, format, v.get<double>());
  return buf;
}

inline void print_eval_table(std::ostream& out, const nlohmann::ordered_json& r, bool plan, bool video) {
  char line[256];
  if (plan) {
    out << "planning (metres; collision rate)  L2@1s   L2@2s   L2@3s  avgL2@3s  coll@1s coll@2s coll@3s\n";
    for (const char* name : {"model", "model_best_of_k", "constant_velocity", "constant_turn", "ground_truth"}) {
      if (!r.contains(name)) continue;
      const auto& m = r[name];
      std::snprintf(line, sizeof line, "  %-32s %6s  %6s  %6s  %8s  %7s %7s %7s\n", name,
                    cell(m["l2_1s"], "%.3f").c_str(), cell(m["l2_2s"], "%.3f").c_str(),
                    cell(m["l2_3s"], "%.3f").c_str(), cell(m["l2_avg_3s"], "%.3f").c_str(),
                    cell(m["collision_rate_1s"], "%.3f").c_str(), cell(m["collision_rate_2s"], "%.3f").c_str(),
                    cell(m["collision_rate_3s"], "%.3f").c_str());
      out << line;
    }
  }
  if (video) {
    const std::size_t N = r["model"]["psnr"].size();
    out << "video (PSNR dB / SSIM per horizon)";
    for (std::size_t h = 0; h < N; ++h) out << "      h" << h + 1;
    out << "\n";
    for (const char* name : {"model", "repeat_last", "autoencoder"})
      for (const char* metric : {"psnr", "ssim"}) {
        std::snprintf(line, sizeof line, "  %-32s", (std::string(name) + " " + metric).c_str());
        out << line;
        for (std::size_t h = 0; h < N; ++h) {
          std::snprintf(line, sizeof line, " %7s", cell(r[name][metric][h], metric[0] == 'p' ? "%.2f" : "%.4f").c_str());
          out << line;
        }
        out << "\n";
      }
  }
}

inline void print_control_table(std::ostream& out, const nlohmann::ordered_json& c) {
  char line[256];
  std::snprintf(line, sizeof line, "control (turn left vs right, yaw +-%d deg, %d frame(s))  scenes  agree   rate   shift px min/median/max\n",
                c["yaw_deg"].get<int>(), c["frames"].get<int>());
  out << line;
  std::snprintf(line, sizeof line, "  %-52s %6d  %5d  %5s   %s / %s / %s\n", "model", c["scenes"].get<int>(),
                c["agree"].get<int>(), cell(c["agree_rate"], "%.3f").c_str(), cell(c["shift_min_px"], "%.0f").c_str(),
                cell(c["shift_median_px"], "%.0f").c_str(), cell(c["shift_max_px"], "%.0f").c_str());
  out << line;
}

// ---- the command ----------------------------------------------------------------------------

inline std::vector<eval::EvalClip> read_clip_set(const EvalOptions& o, const WorldModelConfig& wc) {
  auto folders = eval::find_clip_folders(o.clips);
  if (o.limit && static_cast<std::size_t>(*o.limit) < folders.size()) folders.resize(static_cast<std::size_t>(*o.limit));
  const eval::ClipNeeds need{static_cast<std::size_t>(wc.condition_frames), o.plan ? eval::kPlanWaypoints : 0,
                             o.video ? static_cast<std::size_t>(o.horizon) : 0};
  std::vector<eval::EvalClip> clips;
  for (const auto& dir : folders) {
    clips.push_back(eval::read_clip(dir));
    eval::check_clip(clips.back(), need);
  }
  return clips;
}

// This process's share of the clips scored (every clip when alone), up to --batch clips of the
// share at a time, as one message.
inline std::string score_share(const std::vector<eval::EvalClip>& clips, const EvalOptions& opt, const ModelFiles& files,
                               const ComputeOptions& compute, const Job& job) {
  const Console& con = job.con;
  const auto engine = make_engine(compute);
  cpu::Context ctx(compute.threads);
  engine->load_dcae(files, con);
  engine->load_world(files, con);
  const Console silent{con.out, con.err, true, false};
  const EvalContext e{*engine, ctx, files.configs.world, opt, size_policy(opt.fit), silent};
  const auto share = dist::share_size(clips.size(), job.group->rank(), job.group->size());
  Progress bar(con, "eval    ", static_cast<std::int64_t>(share), "clip");
  return share_message_in_batches(*job.group, clips.size(), static_cast<std::size_t>(opt.batch),
                                  [&](const std::vector<std::size_t>& indices, const ItemWriter& item) {
    std::vector<const eval::EvalClip*> batch;
    std::vector<std::uint64_t> seeds;  // clip i: seed + i, whatever batch it runs in
    for (const std::size_t i : indices) batch.push_back(&clips[i]), seeds.push_back(opt.sample.seed + i);
    const std::vector<ClipScores> scores = evaluate_batch(batch, seeds, e);
    for (std::size_t k = 0; k < indices.size(); ++k) {
      put_scores(item(indices[k]), scores[k]);
      bar.advance();
    }
  });
}

inline int run_eval(const ParsedArgs& a, const Console& console) {
  const ComputeOptions compute = compute_options(a);
  const Job job = join_job(console, compute);
  const Console& con = job.con;
  const ModelFiles files = resolve_models(a, true, true);
  const WorldModelConfig& wc = files.configs.world;
  const EvalOptions opt = eval_options(a, files.configs);
  EPONA_CHECK(!opt.plan || wc.traj_len >= std::int64_t(eval::kPlanWaypoints), "eval: the model plans ", wc.traj_len,
              " waypoint(s); L2 at 1/2/3 s needs ", eval::kPlanWaypoints, " (or pass --no-plan)");
  const std::vector<eval::EvalClip> clips = read_clip_set(opt, wc);  // every clip checked before any work
  con.note("evaluating ", clips.size(), " clip(s) from ", opt.clips.string(), ": ",
           describe(opt.samplers, opt.plan, opt.video || opt.control), ", seed ", opt.sample.seed, " + clip index",
           opt.video ? ", video horizons 1.." + std::to_string(opt.horizon) : std::string(", no video"),
           opt.control ? ", control at +-" + std::to_string(opt.control_yaw) + " deg" : std::string(),
           opt.plan && opt.planning.hypotheses > 1 ? ", " + describe(opt.planning) : std::string(), batch_note(opt.batch),
           job.split_note());

  const std::vector<std::string> by_rank =
      run_on_every_rank(*job.group, [&] { return score_share(clips, opt, files, compute, job); });
  if (!job.group->is_root()) return 0;  // rank 0 reports, and fails for every rank
  const auto scores = items_in_order<ClipScores>(by_rank, clips.size(), get_scores);
  auto settings = settings_json(a, files, compute, opt, wc);
  settings["processes"] = job.group->size();
  const auto report = report_json(scores, settings, opt);
  io::write_atomically(opt.json, report.dump(2) + "\n");
  print_eval_table(con.out, report, opt.plan, opt.video);
  if (opt.control) print_control_table(con.out, report["control"]);
  con.out << "wrote " << opt.json.string() << " (" << clips.size() << " clip(s); FID and FVD not computed)\n";
  return 0;
}

}  // namespace epona::app
