// python/epona_module.cpp — the `epona` Python module (pybind11): the world model and DC-AE loaded
// by the CLI's loaders (apps/epona/models.hpp: the bundled model, safetensors or official .pkl) on
// the CPU or on CUDA, with float32 or bf16 weights, and thin wrappers over the library — encode,
// decode, plan, predict_next, rollout and WorldSession — with NumPy arrays in and out. The model
// is a python::ModelApi (python/model_api.hpp): ModelOf<Cpu, float|bf16> here, ModelOf<Cuda, …>
// from python/cuda_model.cu (nvcc) when built with CUDA, so this file stays plain C++.
// Float inputs are viewed in place when they are C-contiguous float32 (else NumPy converts them
// once); images are copied (uint8 HxWx3 -> the model's float NCHW); results go to NumPy without a
// copy (the array owns the tensor; decoded images are gathered once into one (N, H, W, 3) buffer).
// The GIL is released while the model computes; one call at a time runs on a model (a mutex), so
// threads may share it. epona::Error becomes epona.Error (a RuntimeError) with the library's message.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/domain/poses.hpp"
#include "epona/domain/world_session.hpp"
#include "epona/flow/solvers.hpp"
#include "epona/io/image.hpp"
#include "epona/model/latent_layout.hpp"
#include "epona/model/plan_choice.hpp"
#include "epona/model/rollout.hpp"
#include "epona/model/world_model.hpp"
#include "epona/models.hpp"
#include "model_api.hpp"
#include "model_of.hpp"

namespace py = pybind11;
using namespace epona;

namespace {

using FloatIn = py::array_t<float, py::array::c_style | py::array::forcecast>;
using ByteIn = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>;

// ---- arrays ------------------------------------------------------------------------------

// A NumPy array owning `t` (no copy): the capsule keeps the tensor, and so its storage, alive.
py::array to_numpy(Tensor<float, Cpu> t) {
  auto* owned = new Tensor<float, Cpu>(std::move(t));
  py::capsule keep(owned, [](void* p) { delete static_cast<Tensor<float, Cpu>*>(p); });
  return py::array_t<float>(std::vector<py::ssize_t>(owned->shape().begin(), owned->shape().end()), owned->data(),
                            keep);
}

// Images (N, H, W, 3) uint8 owning `images`' bytes (moved, not copied).
py::array to_numpy(std::vector<io::Image> images) {
  const py::ssize_t n = static_cast<py::ssize_t>(images.size());
  const py::ssize_t H = n ? images[0].height : 0, W = n ? images[0].width : 0;
  auto* bytes = new std::vector<std::uint8_t>();
  bytes->reserve(static_cast<std::size_t>(n * H * W * 3));
  for (auto& img : images) bytes->insert(bytes->end(), img.rgb.begin(), img.rgb.end());
  py::capsule keep(bytes, [](void* p) { delete static_cast<std::vector<std::uint8_t>*>(p); });
  return py::array_t<std::uint8_t>({n, H, W, py::ssize_t{3}}, bytes->data(), keep);
}

py::array to_numpy(io::Image image) {
  auto* bytes = new std::vector<std::uint8_t>(std::move(image.rgb));
  py::capsule keep(bytes, [](void* p) { delete static_cast<std::vector<std::uint8_t>*>(p); });
  return py::array_t<std::uint8_t>({py::ssize_t(image.height), py::ssize_t(image.width), py::ssize_t{3}},
                                   bytes->data(), keep);
}

Shape shape_of(const py::array& a) { return Shape(a.shape(), a.shape() + a.ndim()); }

// A float32 array viewed as a tensor of `dims` dimensions (no copy; the array outlives the call).
Tensor<float, Cpu> view(const FloatIn& a, py::ssize_t dims, const char* what, const char* expected) {
  EPONA_CHECK(a.ndim() == dims, what, " must be ", expected, ", got shape ", shape_str(shape_of(a)));
  return Tensor<float, Cpu>::view(const_cast<float*>(a.data()), shape_of(a));
}

// uint8 images (N, H, W, 3), or one (H, W, 3) -> io::Image each (a copy: io::Image owns its bytes).
std::vector<io::Image> images_of(const ByteIn& a, const char* what) {
  const bool one = a.ndim() == 3;
  EPONA_CHECK((one || a.ndim() == 4) && a.shape(a.ndim() - 1) == 3, what,
              " must be uint8 (N, H, W, 3) or (H, W, 3) RGB, got shape ", shape_str(shape_of(a)));
  const std::int64_t n = one ? 1 : a.shape(0), H = a.shape(a.ndim() - 3), W = a.shape(a.ndim() - 2);
  std::vector<io::Image> out;
  for (std::int64_t i = 0; i < n; ++i) {
    io::Image img(H, W);
    std::copy_n(a.data() + i * H * W * 3, H * W * 3, img.rgb.data());
    out.push_back(std::move(img));
  }
  return out;
}

// Motions (F, 3): x metres forward, y metres left, yaw degrees; one row per frame.
io::PoseSequence poses_of(const FloatIn& a) {
  EPONA_CHECK(a.ndim() == 2 && a.shape(1) == 3, "poses must be float (F, 3) rows of x, y, yaw; got shape ",
              shape_str(shape_of(a)));
  io::PoseSequence p;
  for (py::ssize_t i = 0; i < a.shape(0); ++i) {
    p.x.push_back(a.at(i, 0)), p.y.push_back(a.at(i, 1)), p.yaw.push_back(a.at(i, 2));
  }
  return p;
}

std::optional<Motion> motion_of(const std::optional<FloatIn>& a) {
  if (!a) return std::nullopt;
  EPONA_CHECK(a->size() == 3, "an action must hold 3 values (x metres forward, y metres left, yaw degrees); got shape ",
              shape_str(shape_of(*a)));
  return Motion{a->data()[0], a->data()[1], a->data()[2]};
}

// `f()` with the GIL released (no Python object may be touched inside).
template <class F>
auto without_gil(F&& f) {
  py::gil_scoped_release unlocked;
  return f();
}

// steps: each DiT's (default the config's); solver: each DiT's flow solver by name (default Euler,
// the official), as the CLI's --steps and --solver.
SampleOptions sampling(std::optional<std::int64_t> steps, std::uint64_t seed, const std::optional<std::string>& solver) {
  SampleOptions o;
  o.steps = steps;
  o.seed = seed;
  if (solver) o.solver = flow::parse_solver(*solver);
  return o;
}

model::PlanChoice plan_choice(const std::string& name) {
  const auto rule = model::plan_choice_named(name);
  EPONA_CHECK(rule.has_value(), "choose '", name, "': one of 'medoid', 'mean'");
  return *rule;
}

// ---- the model ---------------------------------------------------------------------------

// The world model and DC-AE of one checkpoint pair, and the lock that serialises their use.
struct Model {
  std::mutex mutex;
  std::string world_file, dcae_file;
  model::PlanningRule planner;  // the rule the model's configs.json recommends ("planner"), as the CLI reads it
  std::unique_ptr<python::ModelApi> api;

  const WorldModelConfig& config() const { return api->config(); }
  // `f()` with the GIL released and the model to itself; results become arrays after it returns.
  template <class F>
  auto locked(F&& f) {
    return without_gil([&] {
      std::lock_guard lock(mutex);
      return f();
    });
  }

  // The window's inputs, checked and viewed (with the GIL: they are the caller's arrays).
  struct WindowInput {
    Tensor<float, Cpu> latents;  // (F, C, h, w), a view of the array
    io::PoseSequence poses;
  };
  WindowInput window_input(const FloatIn& latents, const FloatIn& poses) const {
    const auto& c = config();
    WindowInput in{view(latents, 4, "latents", "float32 (F, C, h, w)"), poses_of(poses)};
    check_shape(in.latents, {c.condition_frames, c.token_dim(), c.latent_h(), c.latent_w()}, "latents");
    EPONA_CHECK(static_cast<std::int64_t>(in.poses.size()) == c.condition_frames, "poses hold ", in.poses.size(),
                " row(s); the window needs one per frame, ", c.condition_frames);
    return in;
  }
  // The window (batch 1) as the CLI makes it, on the host; inside locked() (it uses the host context).
  History window(const WindowInput& in) { return model::make_window(api->host(), in.latents, in.poses); }
  // Tokens (N, L, C) -> latents (N, C, h, w); inside locked().
  Tensor<float> latents_of(const Tensor<float>& tokens) {
    return tokens_to_latent(api->host(), tokens, config().latent_h(), config().latent_w());
  }
};

// The backend and weight type by name (checked before any file is read).
app::ComputeOptions compute_options(const std::string& backend, const std::string& dtype, int threads) {
  EPONA_CHECK(backend == "cpu" || backend == "cuda", "backend '", backend, "': one of 'cpu', 'cuda'");
  const bool bf16 = dtype == "bfloat16" || dtype == "bf16";
  EPONA_CHECK(bf16 || dtype == "float32" || dtype == "fp32", "dtype '", dtype, "': one of 'float32', 'bfloat16'");
  EPONA_CHECK(threads >= 0, "threads must be 0 (every hardware thread) or more, got ", threads);
  app::ComputeOptions c;
  c.backend = backend, c.bf16_weights = bf16, c.threads = threads;
  return c;
}

// The models on the chosen backend: bf16 weights are the CLI's --dtype bfloat16 (stored in bf16;
// on the CPU activations stay float32, on the GPU they are bf16).
std::unique_ptr<python::ModelApi> make_model(const app::ModelFiles& f, const app::ComputeOptions& c,
                                             const app::Console& con) {
  if (c.backend == "cuda") {
#if defined(EPONA_PYTHON_CUDA)
    return python::make_cuda_model(f, c, con);
#else
    fail("backend 'cuda': this epona module was built without CUDA (build it with -DEPONA_CUDA=ON -DEPONA_PYTHON=ON "
         "on a machine with nvcc, docs/python.md); use backend='cpu'");
#endif
  }
  if (c.bf16_weights) return std::make_unique<python::ModelOf<Cpu, bf16>>(f, c, con);
  return std::make_unique<python::ModelOf<Cpu, float>>(f, c, con);
}

// Loads through the CLI's loaders: the same defaults, files and messages as `epona plan`.
std::shared_ptr<Model> load_model(std::optional<std::string> weights, std::optional<std::string> dcae,
                                  std::optional<std::string> config, int threads, const std::string& dtype,
                                  bool verbose, const std::string& backend) {
  const app::ComputeOptions compute = compute_options(backend, dtype, threads);
  std::map<std::string, std::string> options;
  if (weights) options["weights"] = *weights;
  if (dcae) options["dcae"] = *dcae;
  if (config) options["config"] = *config;
  const app::ModelFiles files = app::resolve_models(app::ParsedArgs("epona.load", options, {}), true, true);
  const app::Console con{std::cout, std::cerr, !verbose};
  auto m = std::make_shared<Model>();
  py::gil_scoped_release unlocked;
  m->api = make_model(files, compute, con);
  m->world_file = files.world, m->dcae_file = files.dcae;
  m->planner = files.configs.planner;
  return m;
}

// Built with CUDA and a CUDA device present: backend="cuda" can load.
bool cuda_available() {
#if defined(EPONA_PYTHON_CUDA)
  return python::cuda_device_present();
#else
  return false;
#endif
}

py::array encode_images(Model& m, const ByteIn& images) {
  const auto frames = images_of(images, "images");
  return to_numpy(m.locked([&] { return m.api->encode(frames); }));
}

py::array decode_latents(Model& m, const FloatIn& latents, bool video) {
  const Tensor<float, Cpu> z = view(latents, 4, "latents", "float32 (N, C, h, w)");
  return to_numpy(m.locked([&] { return m.api->decode(z, video); }));
}

// One plan (traj_len, 3): plan() itself for one hypothesis, else the one `choose` picks of K.
py::array plan_trajectory(Model& m, const FloatIn& latents, const FloatIn& poses, std::optional<std::int64_t> steps,
                          std::uint64_t seed, std::int64_t hypotheses, const std::string& choose,
                          const std::optional<std::string>& solver) {
  const auto in = m.window_input(latents, poses);
  const model::PlanChoice rule = plan_choice(choose);
  const SampleOptions opt = sampling(steps, seed, solver);
  return to_numpy(m.locked([&] {
    const Tensor<float> plans = m.api->plans(m.window(in), hypotheses, opt);  // (K, traj_len, 3)
    return hypotheses == 1 ? plans[0] : model::choose_plan(plans, rule).chosen;
  }));
}

// All K plans (K, traj_len, 3); hypothesis k draws with seed + k*0x9E3779B9 (row 0 is plan()'s).
py::array plan_hypotheses(Model& m, const FloatIn& latents, const FloatIn& poses, std::int64_t hypotheses,
                          std::optional<std::int64_t> steps, std::uint64_t seed, const std::optional<std::string>& solver) {
  const auto in = m.window_input(latents, poses);
  const SampleOptions opt = sampling(steps, seed, solver);
  return to_numpy(m.locked([&] { return m.api->plans(m.window(in), hypotheses, opt); }));
}

// The next latent (C, h, w) and the plan that drove it (None when the action was given).
py::tuple predict_latent(Model& m, const FloatIn& latents, const FloatIn& poses, const std::optional<FloatIn>& action,
                         std::optional<std::int64_t> steps, std::uint64_t seed, const std::optional<std::string>& solver) {
  const auto in = m.window_input(latents, poses);
  const std::optional<Motion> a = motion_of(action);
  const SampleOptions opt = sampling(steps, seed, solver);
  const StepResult r = m.locked([&] {
    std::optional<NextAction> next;
    if (a) next = action_of(*a);
    StepResult out = m.api->predict_next(m.window(in), next, opt);
    out.latent = m.latents_of(out.latent)[0];
    return out;
  });
  return py::make_tuple(to_numpy(r.latent), a ? py::object(py::none()) : py::object(to_numpy(r.trajectory[0])));
}

// model::rollout (self-predicted): trajectories (N, traj_len, 3) and latents (N, C, h, w).
py::tuple roll_out_frames(Model& m, const FloatIn& latents, const FloatIn& poses, std::int64_t frames,
                          std::optional<std::int64_t> steps, std::uint64_t seed, const std::optional<std::string>& solver) {
  const auto in = m.window_input(latents, poses);
  const SampleOptions opt = sampling(steps, seed, solver);
  const RolloutResult r = m.locked([&] {
    RolloutResult out = m.api->rollout(m.window(in), RolloutOptions{frames, opt});
    out.latents = m.latents_of(out.latents);
    return out;
  });
  const auto& c = m.config();
  return py::make_tuple(to_numpy(r.trajectories.reshape({frames, c.traj_len, 3})), to_numpy(r.latents));
}

// ---- files -------------------------------------------------------------------------------

// A PNG/JPEG as uint8 (H, W, 3) RGB (grayscale, RGBA and 16-bit converted), as the CLI reads frames.
py::array read_image(const std::string& path) {
  io::ImageReadOptions opt;
  opt.convert_to_rgb8 = true;
  return to_numpy(without_gil([&] { return io::read_image(path, opt); }));
}

void write_png(const std::string& path, const ByteIn& image) {
  auto images = images_of(image, "image");
  EPONA_CHECK(images.size() == 1, "write_png writes one image (H, W, 3), got ", images.size());
  py::gil_scoped_release unlocked;
  io::write_png(path, images[0]);
}

// A poses file (the CLI's --poses: .csv/.json, the demo's folder, 4x4 poses) as float32 (N, 3).
py::array load_poses(const std::string& path) {
  const io::PoseSequence p = io::load_poses(path);
  Tensor<float, Cpu> t({static_cast<std::int64_t>(p.size()), 3});
  for (std::size_t i = 0; i < p.size(); ++i) {
    const auto r = static_cast<std::int64_t>(i);
    t.at(r, 0) = p.x[i], t.at(r, 1) = p.y[i], t.at(r, 2) = p.yaw[i];
  }
  return to_numpy(std::move(t));
}

// ---- the session -------------------------------------------------------------------------

struct Session {
  std::shared_ptr<Model> model;  // keeps the model the session refers to alive
  std::unique_ptr<python::SessionApi> session;
  Session(std::shared_ptr<Model> m, std::optional<std::int64_t> steps, std::uint64_t seed,
          const std::optional<std::string>& solver)
      : model(m), session(make(*m, sampling(steps, seed, solver))) {}
  // Under the model's lock: a session on a device backend makes a host context, which sets the
  // process's thread count while another thread may be computing.
  static std::unique_ptr<python::SessionApi> make(Model& m, const SampleOptions& opt) {
    return m.locked([&] { return m.api->session(opt); });
  }

  void reset(const ByteIn& frames, const FloatIn& poses) {
    const auto images = images_of(frames, "frames");
    const io::PoseSequence p = poses_of(poses);
    model->locked([&] { session->reset(images, p); });
  }

  // (frame (H, W, 3) uint8, trajectory (traj_len, 3) or None when the action was given).
  py::tuple step(const std::optional<FloatIn>& action) {
    const std::optional<Motion> a = motion_of(action);
    SessionStep s = model->locked([&] { return session->step(a); });
    py::object traj = s.trajectory.empty() ? py::object(py::none()) : py::object(to_numpy(s.trajectory));
    return py::make_tuple(to_numpy(std::move(s.frame)), traj);
  }

  // The window the next step sees: latents (F, C, h, w) and motions (F, 3).
  py::tuple window() {
    std::lock_guard lock(model->mutex);
    const History& h = session->window();
    const std::int64_t F = model->config().condition_frames;
    Tensor<float, Cpu> poses({F, 3});
    for (std::int64_t f = 0; f < F; ++f)
      poses.at(f, 0) = h.rel_pose.at(0, f, 0), poses.at(f, 1) = h.rel_pose.at(0, f, 1), poses.at(f, 2) = h.rel_yaw.at(0, f, 0);
    return py::make_tuple(to_numpy(model->latents_of(h.latents[0])), to_numpy(poses));  // a copy: the window slides in place
  }
};

}  // namespace

constexpr const char* kModuleDoc = R"(epona: the Epona driving world model — plan, predict the next frame, roll out, encode and
decode — on the CPU or on CUDA, with float32 or bfloat16 weights.

    model = epona.load(backend="cpu", dtype="float32")   # or backend="cuda", dtype="bfloat16"
    latents = model.encode(frames)                        # uint8 (F, H, W, 3) -> (F, C, h, w)
    plan = model.plan(latents, poses, hypotheses=8, choose="medoid")

backend="cuda" needs a module built with CUDA (-DEPONA_CUDA=ON -DEPONA_PYTHON=ON) and a GPU:
epona.cuda_available() says whether both hold. Inputs and results are NumPy arrays on the host
whatever the backend. Errors are epona.Error (a RuntimeError) with the library's message.)";

PYBIND11_MODULE(epona, m) {
  m.doc() = kModuleDoc;
  py::register_exception<Error>(m, "Error", PyExc_RuntimeError);

  py::class_<Model, std::shared_ptr<Model>>(m, "Model", "A loaded world model and DC-AE on one backend (see epona.load)")
      .def_property_readonly("backend", [](const Model& x) { return std::string(x.api->backend()); })
      .def_property_readonly("dtype", [](const Model& x) { return std::string(x.api->dtype()); })
      .def_property_readonly("image_size", [](const Model& x) { return py::make_tuple(x.config().image_h, x.config().image_w); })
      .def_property_readonly("condition_frames", [](const Model& x) { return x.config().condition_frames; })
      .def_property_readonly("traj_len", [](const Model& x) { return x.config().traj_len; })
      .def_property_readonly("latent_shape", [](const Model& x) {
        return py::make_tuple(x.config().token_dim(), x.config().latent_h(), x.config().latent_w());
      })
      .def_property_readonly("sampling_steps", [](const Model& x) { return x.config().num_sampling_steps; })
      .def_property_readonly("recommended_planning", [](const Model& x) {
        return py::make_tuple(x.planner.hypotheses, std::string(model::plan_choice_name(x.planner.choose)));
      }, "(hypotheses, choose) of the model's configs.json \"planner\" (the CLI's plan default); (1, 'medoid') if none")
      .def_readonly("world_file", &Model::world_file)
      .def_readonly("dcae_file", &Model::dcae_file)
      .def("encode", &encode_images, py::arg("images"), "uint8 images (N, H, W, 3) or (H, W, 3) -> float32 latents (N, C, h, w)")
      .def("decode", &decode_latents, py::arg("latents"), py::arg("video") = false,
           "float32 latents (N, C, h, w) -> uint8 images (N, H, W, 3); video=True: the temporal decoder over clips")
      .def("plan", &plan_trajectory, py::arg("latents"), py::arg("poses"), py::arg("steps") = py::none(), py::arg("seed") = 0,
           py::arg("hypotheses") = 1, py::arg("choose") = "medoid", py::arg("solver") = py::none(),
           "latents (F, C, h, w) and motions (F, 3) -> the planned trajectory (traj_len, 3): x, y metres, yaw degrees.\n"
           "hypotheses=K > 1: K plans of the scene and the one `choose` picks ('medoid' or 'mean'), as the CLI's\n"
           "plan --hypotheses K --choose RULE; solver: the flow solver by name (default 'euler', the official)")
      .def("plan_hypotheses", &plan_hypotheses, py::arg("latents"), py::arg("poses"), py::arg("hypotheses"),
           py::arg("steps") = py::none(), py::arg("seed") = 0, py::arg("solver") = py::none(),
           "K plans of the scene (K, traj_len, 3); hypothesis k draws with seed + k*0x9E3779B9 (row 0 is plan()'s)")
      .def("predict_next", &predict_latent, py::arg("latents"), py::arg("poses"), py::arg("action") = py::none(),
           py::arg("steps") = py::none(), py::arg("seed") = 0, py::arg("solver") = py::none(),
           "the next latent (C, h, w) and the plan that drove it (None when `action` (x, y, yaw) is given)")
      .def("rollout", &roll_out_frames, py::arg("latents"), py::arg("poses"), py::arg("frames"), py::arg("steps") = py::none(),
           py::arg("seed") = 0, py::arg("solver") = py::none(),
           "self-predicted rollout: (trajectories (N, traj_len, 3), latents (N, C, h, w))");

  m.def("load", &load_model, py::arg("weights") = py::none(), py::arg("dcae") = py::none(), py::arg("config") = py::none(),
        py::arg("threads") = 0, py::arg("dtype") = "float32", py::arg("verbose") = false, py::arg("backend") = "cpu",
        "Loads the world model and DC-AE as the CLI does: without files the bundled model (models/small-synthetic);\n"
        "weights/dcae: official .pkl or .safetensors; config: a configs.json (default: the shipped Epona one).\n"
        "backend: 'cpu' or 'cuda' (the CLI's --backend); dtype: 'float32' or 'bfloat16' weights (the CLI's --dtype).");
  m.def("cuda_available", &cuda_available,
        "True when this module was built with CUDA and a CUDA device is present (backend='cuda' can load)");
#if defined(EPONA_PYTHON_CUDA)
  m.attr("built_with_cuda") = true;
#else
  m.attr("built_with_cuda") = false;
#endif

  m.def("read_image", &read_image, py::arg("path"), "a PNG/JPEG file -> uint8 (H, W, 3) RGB");
  m.def("write_png", &write_png, py::arg("path"), py::arg("image"), "uint8 (H, W, 3) RGB -> a PNG file");
  m.def("load_poses", &load_poses, py::arg("path"),
        "a poses file (as the CLI's --poses) -> float32 (N, 3): x metres forward, y metres left, yaw degrees");
  m.attr("bundled_model_dir") = app::bundled_model().dir;

  py::class_<Session>(m, "WorldSession", "An autoregressive driving session over a loaded model (its backend)")
      .def(py::init<std::shared_ptr<Model>, std::optional<std::int64_t>, std::uint64_t, const std::optional<std::string>&>(),
           py::arg("model"), py::arg("steps") = py::none(), py::arg("seed") = 0, py::arg("solver") = py::none())
      .def("reset", &Session::reset, py::arg("frames"), py::arg("poses"),
           "the last F frames, uint8 (F, H, W, 3), and the motion into each, float (F, 3): encoded once")
      .def("step", &Session::step, py::arg("action") = py::none(),
           "one step: (frame uint8 (H, W, 3), the plan (traj_len, 3) or None when `action` (x, y, yaw) is given)")
      .def("window", &Session::window, "the window the next step sees: (latents (F, C, h, w), motions (F, 3))")
      .def_property_readonly("steps_taken", [](const Session& s) { return s.session->steps_taken(); })
      .def_property_readonly("arena_capacity", [](const Session& s) { return s.session->arena_capacity(); });
}

// stb is compiled in exactly one translation unit, after every other include.
#include "epona/io/stb_implementation.hpp"
