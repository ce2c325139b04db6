// Tests for epona/model/config.hpp, model/parameter_counts.hpp and domain/config_json.hpp: the
// golden configs.json is read and every value compared with the JSON itself (generic, no numbers
// of this set), the derived sizes with its "derived"/"mst"/"vis_dit"/"traj_dit"/"dcae" sections,
// the parameter counts (from the parameter tree) with the weights listed in manifest.json; defaults equal the shipped model; every
// invalid or malformed input is refused with an error that names the problem.
#include <doctest/doctest.h>

#include <cstdlib>
#include <fstream>
#include <functional>
#include <string>

#include "epona/domain/config_json.hpp"
#include "epona/model/config.hpp"
#include "epona/model/parameter_counts.hpp"
#include "../golden_dir.hpp"
#include "../files.hpp"

using namespace epona;
using epona::test::read_json;
using epona::test::golden_dir;
using nlohmann::json;

namespace {

const json& golden_configs() {
  static const json j = read_json(golden_dir() + "/configs.json");
  return j;
}
const json& golden_manifest() {
  static const json j = read_json(golden_dir() + "/manifest.json");
  return j;
}

// Every key we write must equal the same key of `expected` (numbers compare by value).
void check_subset(const json& ours, const json& expected, const std::string& path) {
  for (auto it = ours.begin(); it != ours.end(); ++it) {
    const std::string key = path + "." + it.key();
    REQUIRE_MESSAGE(expected.contains(it.key()), "golden JSON lacks " << key);
    if (it->is_object()) {
      check_subset(*it, expected.at(it.key()), key);
    } else {
      CHECK_MESSAGE(*it == expected.at(it.key()), key << ": ours " << it->dump() << ", golden "
                                                      << expected.at(it.key()).dump());
    }
  }
}

// Sum of numel over the manifest's weights whose names pass `keep` ({name: shape} or
// {name: [shape, dtype]}).
double manifest_numel(const json& weights, const std::function<bool(const std::string&)>& keep) {
  double total = 0;
  for (auto it = weights.begin(); it != weights.end(); ++it) {
    if (!keep(it.key())) continue;
    const json& shape = (!it->empty() && (*it)[0].is_array()) ? (*it)[0] : *it;
    double n = 1;
    for (const auto& d : shape) n *= d.get<double>();
    total += n;
  }
  return total;
}

bool starts_with(const std::string& s, const char* p) { return s.rfind(p, 0) == 0; }
bool is_bn_buffer(const std::string& k) {
  for (const char* b : {".running_mean", ".running_var", ".num_batches_tracked"})
    if (k.size() >= std::strlen(b) && k.compare(k.size() - std::strlen(b), std::string::npos, b) == 0) return true;
  return false;
}

// The message of the epona::Error that f throws ("" if it throws nothing).
template <class F>
std::string error_of(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

io::ModelConfigs golden() { return io::load_configs(golden_dir() + "/configs.json"); }

}  // namespace

TEST_CASE("golden configs.json: every world-model value equals the JSON") {
  const auto c = golden();
  check_subset(io::to_json(c.world), golden_configs().at("world_model_config"), "world_model_config");
}

TEST_CASE("golden configs.json: derived sizes match its derived / mst / dit sections") {
  const auto w = golden().world;
  const json& d = golden_configs().at("derived");
  CHECK(w.latent_h() == d.at("latent_h").get<std::int64_t>());
  CHECK(w.latent_w() == d.at("latent_w").get<std::int64_t>());
  CHECK(w.img_tokens() == d.at("img_tokens").get<std::int64_t>());
  CHECK(constants::pose_tokens == d.at("pose_tokens").get<int>());
  CHECK(constants::yaw_tokens == d.at("yaw_tokens").get<int>());
  CHECK(w.tokens_per_frame() == d.at("total_tokens").get<std::int64_t>());
  CHECK(w.token_dim() == d.at("vae_emb_dim").get<std::int64_t>());
  CHECK(constants::traj_token_size == d.at("traj_token_size").get<int>());
  CHECK(w.mst_head_dim() == d.at("mst_head_dim").get<std::int64_t>());
  CHECK(w.mst_sequence_tokens() == d.at("mst_block_size_attr").get<std::int64_t>());

  const json& mst = golden_configs().at("mst");
  CHECK(w.n_embd == mst.at("n_embd").get<std::int64_t>());
  CHECK(w.n_head == mst.at("n_head").get<std::int64_t>());
  CHECK(w.mst_depth() == mst.at("n_layer_causal_time_space").get<std::int64_t>());
  CHECK(constants::fourier_embed_dim == mst.at("yaw_pose_emb_dim").get<int>());
  CHECK(constants::mst_time_emb_rows == mst.at("time_emb_rows").get<int>());
  CHECK(constants::mst_rope_theta == mst.at("rope_theta").get<double>());
  CHECK(constants::mst_layernorm_eps == mst.at("layernorm_eps").get<double>());

  struct Dit {
    const char* section;
    std::int64_t in, hidden, heads, depth, single, vec_in;
    std::array<std::int64_t, 3> axes;
  };
  for (const Dit& dit : {Dit{"vis_dit", w.token_dim(), w.n_embd_dit, w.n_head_dit, w.vis_double_blocks(),
                             w.vis_single_blocks(), w.vis_vec_in_dim(), w.axes_dim_dit},
                         Dit{"traj_dit", constants::traj_token_size, w.n_embd_dit_traj, w.n_head_dit_traj,
                             w.traj_double_blocks(), w.traj_single_blocks(), -1, w.axes_dim_dit_traj}}) {
    CAPTURE(dit.section);
    const json& s = golden_configs().at(dit.section);
    CHECK(dit.in == s.at("in_channels").get<std::int64_t>());
    CHECK(dit.in == s.at("out_channels").get<std::int64_t>());
    CHECK(w.context_in_dim() == s.at("context_in_dim").get<std::int64_t>());
    CHECK(dit.hidden == s.at("hidden_size").get<std::int64_t>());
    CHECK(dit.heads == s.at("num_heads").get<std::int64_t>());
    CHECK(dit.depth == s.at("depth").get<std::int64_t>());
    CHECK(dit.single == s.at("depth_single_blocks").get<std::int64_t>());
    CHECK(json(dit.axes) == s.at("axes_dim"));
    CHECK(constants::dit_rope_theta == s.at("theta").get<double>());
    CHECK(double(constants::dit_mlp_ratio) == s.at("mlp_ratio").get<double>());
    if (dit.vec_in >= 0) CHECK(dit.vec_in == s.at("vec_in_dim").get<std::int64_t>());
  }
}

TEST_CASE("golden configs.json: DC-AE values equal the JSON, derived sizes match") {
  const auto c = golden().dcae;
  const json& g = golden_configs().at("dcae");
  check_subset(io::to_json(c), g, "dcae");
  CHECK(json({c.latent_h(), c.latent_w()}) == g.at("latent_size"));
  CHECK(c.token_size() == g.at("token_size").get<std::int64_t>());
  CHECK(c.condition_frames == g.at("temporal_frames").get<std::int64_t>());
  CHECK(c.temporal_head_dim() == g.at("temporal_block").at("head_dim").get<std::int64_t>());
  CHECK(c.temporal_ffn_hidden == DcaeConfig::llama_ffn_hidden(c.temporal_dim));
  CHECK(constants::dcae_trms2d_eps == g.at("trms2d_eps").get<double>());
  CHECK(constants::dcae_batchnorm_eps == g.at("batchnorm_eps").get<double>());
  CHECK(constants::dcae_litemla_head_dim == g.at("litemla").at("dim").get<int>());
  CHECK(constants::dcae_litemla_eps == g.at("litemla").at("eps").get<double>());
}

TEST_CASE("golden configs.json: hard-coded constants equal its constants section") {
  const json& k = golden_configs().at("constants");
  CHECK(constants::fourier_embed_dim == k.at("fourier").at("embed_dim").get<int>());
  CHECK(constants::fourier_max_period == k.at("fourier").at("max_period").get<double>());
  CHECK(constants::timestep_embed_dim == k.at("timestep_embedding").at("dim").get<int>());
  CHECK(constants::timestep_max_period == k.at("timestep_embedding").at("max_period").get<double>());
  CHECK(constants::timestep_time_factor == k.at("timestep_embedding").at("time_factor").get<double>());
  CHECK(constants::dit_rope_theta == k.at("flux_rope_theta").get<double>());
  CHECK(constants::dit_layernorm_eps == k.at("flux_layernorm_eps").get<double>());
  CHECK(constants::dit_rmsnorm_eps == k.at("flux_rmsnorm_eps").get<double>());
  CHECK(constants::schedule_base_shift == k.at("schedule").at("base_shift").get<double>());
  CHECK(constants::schedule_max_shift == k.at("schedule").at("max_shift").get<double>());
  CHECK(constants::schedule_x1 == k.at("schedule").at("x1").get<double>());
  CHECK(constants::schedule_x2 == k.at("schedule").at("x2").get<double>());
  CHECK(constants::tokenizer_x_range_m == k.at("tokenizer").at("x_range").get<double>());
  CHECK(constants::tokenizer_y_range_m == k.at("tokenizer").at("y_range").get<double>());
  CHECK(constants::tokenizer_yaw_range_deg == k.at("tokenizer").at("yaw_range_deg").get<double>());
}

TEST_CASE("parameter counts equal the weights listed in manifest.json") {
  const auto c = golden();
  const json& m = golden_manifest();
  const json& world = m.at("weights_world");
  const json& dcae = m.at("weights_dcae");
  const auto w = model::world_parameter_counts(c.world);
  CHECK(w.mst == manifest_numel(world, [](auto& k) { return starts_with(k, "module.model."); }));
  CHECK(w.vis_dit == manifest_numel(world, [](auto& k) { return starts_with(k, "module.dit."); }));
  CHECK(w.traj_dit == manifest_numel(world, [](auto& k) { return starts_with(k, "module.traj_dit."); }));
  CHECK(w.total == manifest_numel(world, [](auto&) { return true; }));
  const auto d = model::dcae_parameter_counts(c.dcae);
  CHECK(d.encoder == manifest_numel(dcae, [](auto& k) { return starts_with(k, "encoder."); }));
  CHECK(d.decoder == manifest_numel(dcae, [](auto& k) { return starts_with(k, "decoder.") && !is_bn_buffer(k); }));
  CHECK(d.buffers == manifest_numel(dcae, [](auto& k) { return is_bn_buffer(k); }));
  CHECK(d.temporal() ==
        manifest_numel(dcae, [](auto& k) { return starts_with(k, "causal_time_block.") || starts_with(k, "space_block."); }));
  CHECK(d.total == manifest_numel(dcae, [](auto& k) { return !is_bn_buffer(k); }));
}

TEST_CASE("parameter counts need only the values that shape a parameter") {
  // epona info counts a configuration read from a checkpoint's shapes, whose RoPE split may be
  // assumed from another model: the split shapes no parameter.
  WorldModelConfig c;
  c.axes_dim_dit = {2, 2, 2};
  CHECK_THROWS_WITH_AS(c.validate(), doctest::Contains("axes_dim_dit sums to 6"), Error);
  CHECK(model::world_parameter_counts(c).total == model::world_parameter_counts(WorldModelConfig{}).total);
  c.n_head = 3;  // what does shape one is still refused
  CHECK_THROWS_WITH_AS((void)model::world_parameter_counts(c), doctest::Contains("n_head (3) does not divide"), Error);
}

TEST_CASE("defaults are the shipped model (configs/dit_config_dcae_nuplan.py, dc-ae-f32c32-mix)") {
  const WorldModelConfig w;
  CHECK(w.image_h == 512);
  CHECK(w.image_w == 1024);
  CHECK(w.latent_h() == 16);
  CHECK(w.latent_w() == 32);
  CHECK(w.img_tokens() == 512);
  CHECK(w.tokens_per_frame() == 515);
  CHECK(w.condition_frames == 10);
  CHECK(w.n_layer == std::array<std::int64_t, 3>{12, 6, 6});
  CHECK(w.n_embd == 2048);
  CHECK(w.mst_head_dim() == 128);
  CHECK(w.vis_head_dim() == 128);
  CHECK(w.traj_head_dim() == 128);
  CHECK(w.vis_vec_in_dim() == 6144);
  CHECK(w.n_embd_dit_traj == 1024);
  CHECK(w.traj_len == 15);
  CHECK(w.num_sampling_steps == 100);
  CHECK(w.yaw_vocab_size == 512);
  // world-model.md §9.1
  const auto wn = model::world_parameter_counts(w);
  CHECK(wn.mst == 1214533632.0);
  CHECK(wn.vis_dit == 1318191648.0);
  CHECK(wn.traj_dit == 59037443.0);
  CHECK(wn.total == 2591762723.0);
  CHECK_NOTHROW(model::validate_with_size(w));

  const DcaeConfig d;
  CHECK(d.encoder_width_list == DcaeConfig::Ints{128, 256, 512, 512, 1024, 1024});
  CHECK(d.decoder_depth_list == DcaeConfig::Ints{0, 5, 10, 2, 2, 2});
  CHECK(d.condition_frames == 6);
  CHECK(d.token_size() == 512);
  CHECK(d.temporal_ffn_hidden == DcaeConfig::llama_ffn_hidden(32));
  // dcae.md §1
  const auto dn = model::dcae_parameter_counts(d);
  CHECK(dn.encoder == 123172384.0);
  CHECK(dn.decoder == 200184076.0);
  CHECK(dn.temporal() == 287360.0);
  CHECK(dn.total == 323643820.0);
  CHECK(dn.buffers == 12815.0);
  CHECK_NOTHROW(model::validate_with_size(d));
}

TEST_CASE("WorldModelConfig::validate refuses each impossible value") {
  struct Bad {
    std::function<void(WorldModelConfig&)> edit;
    const char* message;
  };
  const Bad cases[] = {
      {[](auto& c) { c.image_h = 0; }, "image_size[0]"},
      {[](auto& c) { c.image_w = -32; }, "image_size[1]"},
      {[](auto& c) { c.image_h = 500; }, "multiples of 32"},
      {[](auto& c) { c.downsample_size = 16; }, "downsample_size"},
      {[](auto& c) { c.patch_size = 2; }, "patch_size"},
      {[](auto& c) { c.vae_embed_dim = 0; }, "vae_embed_dim"},
      {[](auto& c) { c.condition_frames = 51; }, "condition_frames"},
      {[](auto& c) { c.condition_frames = 0; }, "condition_frames"},
      {[](auto& c) { c.block_size = 2; }, "block_size"},
      {[](auto& c) { c.n_layer[0] = 0; }, "n_layer[0]"},
      {[](auto& c) { c.n_layer[1] = -1; }, "n_layer[1]"},
      {[](auto& c) { c.n_layer = {1, 0, 0}; }, "VisDiT needs at least one block"},
      {[](auto& c) { c.n_layer_traj = {0, 0}; }, "TrajDiT needs at least one block"},
      {[](auto& c) { c.n_head = 3; }, "n_head (3) does not divide n_embd"},
      {[](auto& c) { c.n_head = 0; }, "n_head must be"},
      {[](auto& c) { c.n_head_dit = 5; }, "n_head_dit (5) does not divide"},
      {[](auto& c) { c.n_head_dit_traj = 7; }, "n_head_dit_traj (7) does not divide"},
      {[](auto& c) { c.n_embd = 2040, c.n_head = 12; }, "multiple of 4"},
      {[](auto& c) { c.axes_dim_dit = {16, 56, 50}; }, "axes_dim_dit sums to 122"},
      {[](auto& c) { c.axes_dim_dit = {15, 57, 56}; }, "positive and even"},
      {[](auto& c) { c.axes_dim_dit_traj = {0, 64, 64}; }, "axes_dim_dit_traj[0]"},
      {[](auto& c) { c.traj_len = 0; }, "traj_len"},
      {[](auto& c) { c.pose_x_vocab_size = 0; }, "pose_x_vocab_size"},
      {[](auto& c) { c.pose_y_vocab_size = -5; }, "pose_y_vocab_size"},
      {[](auto& c) { c.yaw_vocab_size = 0; }, "yaw_vocab_size"},
      {[](auto& c) { c.pose_x_bound = 0; }, "pose_x_bound"},
      {[](auto& c) { c.yaw_bound = std::nan(""); }, "yaw_bound"},
      {[](auto& c) { c.num_sampling_steps = 0; }, "num_sampling_steps"},
      {[](auto& c) { c.n_embd = std::int64_t{1} << 40; }, "n_embd must be in"},
      {[](auto& c) { c.n_layer[0] = 4000000; }, "n_layer[0] (MST blocks) must be in [1, 256]"},
      {[](auto& c) { c.n_layer_traj[1] = 257; }, "n_layer_traj[1] (TrajDiT single blocks) must be in [0, 256]"},
      {[](auto& c) { c.n_embd = 1 << 20, c.n_head = 8192; }, "the world model would have "},
      {[](auto& c) { c.image_h = 1 << 20, c.image_w = 1 << 20; }, "of activations"},
  };
  for (const auto& bad : cases) {
    WorldModelConfig c;
    bad.edit(c);
    CAPTURE(bad.message);
    CHECK_THROWS_WITH_AS(model::validate_with_size(c), doctest::Contains(bad.message), Error);
  }
  // Several problems are reported together.
  WorldModelConfig c;
  c.traj_len = 0;
  c.yaw_vocab_size = 0;
  const std::string msg = error_of([&] { c.validate(); });
  CHECK(msg.find("traj_len") != std::string::npos);
  CHECK(msg.find("yaw_vocab_size") != std::string::npos);
}

TEST_CASE("DcaeConfig::validate refuses each impossible value") {
  struct Bad {
    std::function<void(DcaeConfig&)> edit;
    const char* message;
  };
  const Bad cases[] = {
      {[](auto& c) { c.image_h = 100; }, "multiples of 32"},
      {[](auto& c) { c.image_w = 0; }, "image_size[1]"},
      {[](auto& c) { c.latent_channels = 0; }, "latent_channels"},
      {[](auto& c) { c.latent_channels = 48, c.temporal_dim = 48, c.temporal_heads = 8; }, "averaging shortcut"},
      {[](auto& c) { c.encoder_width_list.pop_back(); }, "encoder width_list has 5 entries"},
      {[](auto& c) { c.decoder_depth_list.push_back(1); }, "decoder depth_list has 7 entries"},
      {[](auto& c) { c.decoder_norm.resize(3); }, "decoder norm has 3 entries"},
      {[](auto& c) { c.encoder_width_list[2] = 0; }, "encoder width_list[2]"},
      {[](auto& c) { c.decoder_depth_list[3] = -1; }, "decoder depth_list[3]"},
      {[](auto& c) { c.encoder_depth_list[0] = 1; }, "depth_list[0] must be 0"},
      {[](auto& c) { c.encoder_depth_list[2] = 0; }, "encoder depth_list[2] must be > 0"},
      {[](auto& c) { c.encoder_width_list[4] = 1000; }, "LiteMLA head dim"},
      {[](auto& c) { c.decoder_width_list[2] = 300; }, "2x resampling"},
      {[](auto& c) { c.encoder_block_type[1] = static_cast<DcaeBlockType>(9); }, "block_type[1] is not a known"},
      {[](auto& c) { c.decoder_norm[0] = static_cast<DcaeNorm>(7); }, "norm[0] is not a known"},
      {[](auto& c) { c.decoder_act[5] = static_cast<DcaeAct>(7); }, "act[5] is not a known"},
      {[](auto& c) { c.condition_frames = 0; }, "condition_frames"},
      {[](auto& c) { c.temporal_heads = 3; }, "temporal n_heads (3)"},
      {[](auto& c) { c.temporal_dim = 64; }, "must equal latent_channels"},
      {[](auto& c) { c.temporal_blocks = 0; }, "temporal n_blocks"},
      {[](auto& c) { c.temporal_blocks = 1 << 20; }, "temporal n_blocks must be in [1, 256]"},
      {[](auto& c) { c.encoder_depth_list[3] = 5000; }, "encoder depth_list[3] must be in [0, 256]"},
      {[](auto& c) { c.temporal_rmsnorm_eps = -1; }, "rmsnorm_eps"},
      {[](auto& c) { c.encoder_width_list = {1 << 20, 1 << 20, 1 << 20, 1 << 20, 1 << 20, 1 << 20}; }, "parameters"},
      {[](auto& c) { c.image_h = 1 << 18, c.image_w = 1 << 18; }, "of activations"},
  };
  for (const auto& bad : cases) {
    DcaeConfig c;
    bad.edit(c);
    CAPTURE(bad.message);
    CHECK_THROWS_WITH_AS(model::validate_with_size(c), doctest::Contains(bad.message), Error);
  }
  DcaeConfig off;
  off.add_decoder_temporal = false;  // nuScenes: no temporal blocks, their fields do not matter
  off.temporal_dim = 0;
  CHECK_NOTHROW(model::validate_with_size(off));
  CHECK(model::dcae_parameter_counts(off).temporal() == 0);
}

TEST_CASE("to_json round-trips, and a plain world_model_config object is accepted") {
  const auto c = golden();
  CHECK(io::configs_from_json(io::to_json(c), "roundtrip") == c);
  const io::ModelConfigs real;
  CHECK(io::parse_configs(io::to_json(real).dump(2), "real") == real);

  // Plain object: the DC-AE takes image size, latent width, clip length and flag from it.
  const json& w = golden_configs().at("world_model_config");
  const auto plain = io::parse_configs(w.dump(), "plain.json");
  CHECK(plain.world == c.world);
  CHECK(plain.dcae.image_h == c.world.image_h);
  CHECK(plain.dcae.latent_channels == c.world.vae_embed_dim);
  CHECK(plain.dcae.condition_frames == w.at("temporal_patch_size").get<std::int64_t>());
  CHECK(plain.dcae.add_decoder_temporal == w.at("add_decoder_temporal").get<bool>());
  CHECK(plain.dcae.encoder_width_list == DcaeConfig{}.encoder_width_list);
}

TEST_CASE("the optional planner block: absent = one plan; read, written and round-tripped") {
  json j = golden_configs();
  j.erase("planner");  // the trained set's configuration carries one
  const auto without = io::parse_configs(j.dump(), "configs.json");
  CHECK(without.planner == model::PlanningRule{});
  CHECK(!io::to_json(without).contains("planner"));  // the default is not written
  j["planner"] = {{"hypotheses", 8}, {"choose", "mean"}};
  const auto c = io::parse_configs(j.dump(), "configs.json");
  CHECK(c.planner.hypotheses == 8);
  CHECK(c.planner.choose == model::PlanChoice::mean);
  CHECK(c.world == golden().world);
  CHECK(io::configs_from_json(io::to_json(c), "roundtrip") == c);
  j["planner"] = {{"hypotheses", 4}};  // either key alone; the other keeps its default
  const auto k4 = io::parse_configs(j.dump(), "configs.json").planner;
  CHECK(k4 == model::PlanningRule{4, model::PlanChoice::medoid});
}

TEST_CASE("malformed JSON, missing keys and wrong types give errors naming the key") {
  const std::string broken = error_of([] { io::parse_configs("{\"a\": ", "broken.json"); });
  CHECK(broken.find("broken.json: invalid JSON") != std::string::npos);
  CHECK_THROWS_WITH_AS(io::parse_configs("", "empty.json"), doctest::Contains("invalid JSON"), Error);
  CHECK_THROWS_WITH_AS(io::parse_configs("[1, 2]", "list.json"), doctest::Contains("must be a JSON object"), Error);
  CHECK_THROWS_WITH_AS(io::load_configs(golden_dir() + "/no_such_file.json"), doctest::Contains("does not exist"),
                       Error);
  CHECK_THROWS_WITH_AS(io::load_configs(golden_dir()), doctest::Contains("not a regular file"), Error);

  struct Edit {
    std::function<void(json&)> edit;
    const char* message;
  };
  const Edit edits[] = {
      {[](json& j) { j["world_model_config"].erase("n_head"); }, "missing key 'world_model_config.n_head'"},
      {[](json& j) { j["world_model_config"]["n_head"] = "two"; }, "world_model_config.n_head must be an integer"},
      {[](json& j) { j["world_model_config"]["n_embd"] = 12.5; }, "world_model_config.n_embd must be an integer"},
      {[](json& j) { j["world_model_config"]["image_size"] = 64; }, "world_model_config.image_size must be a list"},
      {[](json& j) { j["world_model_config"]["image_size"] = {64}; }, "image_size must have 2 entries"},
      {[](json& j) { j["world_model_config"]["n_layer"][1] = "x"; }, "world_model_config.n_layer[1]"},
      {[](json& j) { j["world_model_config"]["yaw_bound"] = nullptr; }, "world_model_config.yaw_bound must be a number"},
      {[](json& j) { j["world_model_config"]["condition_frames"] = 99; }, "condition_frames must be in [1, 50]"},
      {[](json& j) { j["world_model_config"] = 3; }, "world_model_config must be a JSON object"},
      {[](json& j) { j.erase("dcae"); }, "missing key 'dcae'"},
      {[](json& j) { j["dcae"].erase("image_size"); }, "missing key 'dcae.image_size'"},
      {[](json& j) { j["dcae"]["config"]["encoder"]["block_type"][3] = "Swin"; },
       "dcae.config.encoder.block_type: unknown DC-AE block type 'Swin'"},
      {[](json& j) { j["dcae"]["config"]["decoder"]["norm"][0] = "ln2d"; }, "dcae.config.decoder.norm: unknown DC-AE norm"},
      {[](json& j) { j["dcae"]["config"]["encoder"]["act"] = "gelu"; }, "dcae.config.encoder.act: unknown DC-AE activation"},
      {[](json& j) { j["dcae"]["config"]["decoder"]["width_list"] = "wide"; }, "dcae.config.decoder.width_list must be a list"},
      {[](json& j) { j["dcae"]["config"]["add_decoder_temporal"] = 1; }, "add_decoder_temporal must be true or false"},
      {[](json& j) { j["dcae"]["config"]["use_quant_conv"] = true; }, "dcae.config.use_quant_conv = true is not supported"},
      {[](json& j) { j["dcae"]["config"]["encoder"]["downsample_shortcut"] = "none"; }, "downsample_shortcut"},
      {[](json& j) { j["dcae"]["config"]["token_size"] = 7; }, "dcae.config.token_size (7) does not match"},
      {[](json& j) { j["dcae"]["config"]["decoder"]["latent_channels"] = 16; }, "decoder.latent_channels differs"},
      {[](json& j) { j["dcae"]["temporal_block"]["rope_dim"] = 2; }, "dcae.temporal_block.rope_dim"},
      {[](json& j) { j["dcae"]["temporal_block"]["n_heads"] = 3; }, "dcae.temporal_block.head_dim"},
      {[](json& j) { j["world_model_config"]["vae_embed_dim"] = 16; }, "vae_embed_dim (16) must equal"},
      {[](json& j) { j["dcae"]["config"]["encoder"]["depth_list"][0] = 1; }, "configs.json: DcaeConfig: invalid"},
      {[](json& j) { j["planner"] = 8; }, "planner must be a JSON object"},
      {[](json& j) { j["planner"] = {{"hypotheses", 0}}; }, "planner.hypotheses must be 1..1024, got 0"},
      {[](json& j) { j["planner"] = {{"hypotheses", 1025}}; }, "planner.hypotheses must be 1..1024, got 1025"},
      {[](json& j) { j["planner"] = {{"hypotheses", 2.5}}; }, "planner.hypotheses must be an integer"},
      {[](json& j) { j["planner"] = {{"choose", "best"}}; }, "planner.choose must be \"medoid\" or \"mean\", got \"best\""},
      {[](json& j) { j["planner"] = {{"choose", 1}}; }, "planner.choose must be a string"},
      {[](json& j) { j["planner"] = {{"hypothesis", 8}}; }, "planner: unknown key \"hypothesis\""},
  };
  for (const auto& e : edits) {
    json j = golden_configs();
    e.edit(j);
    CAPTURE(e.message);
    CHECK_THROWS_WITH_AS(io::parse_configs(j.dump(), "configs.json"), doctest::Contains(e.message), Error);
  }
  // Unknown extra keys are ignored.
  json extra = golden_configs();
  extra["world_model_config"]["some_future_key"] = {1, 2, 3};
  extra["dcae"]["config"]["another"] = "x";
  CHECK_NOTHROW(io::parse_configs(extra.dump(), "extra.json"));
  // A plain object with a different VAE is refused.
  json plain = golden_configs().at("world_model_config");
  plain["vae"] = "SD_VAE";
  CHECK_THROWS_WITH_AS(io::parse_configs(plain.dump(), "plain.json"), doctest::Contains("vae"), Error);
}
