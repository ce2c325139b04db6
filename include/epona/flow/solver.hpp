// epona/flow/solver.hpp — a rectified-flow ODE solver as one template over an update rule: it
// integrates dx/dt = v(x, t) in place over a time grid (t_0 = 0 noise .. t_N = 1 data, the
// schedule of flow/schedule.hpp or any other), calling the velocity once per evaluation. The
// rule (flow/rules.hpp) says which times it evaluates at and how a step combines them; the
// solver owns the loop, the evaluation count and the conversion of the state for a velocity
// that reads another type (the GPU's bf16 DiTs). Nothing here allocates: the state, the
// velocity and the rule's scratch states are the caller's, so a whole sample can be recorded
// once as a CUDA graph.
//
// The velocity contract is the one the DiTs always had: velocity(k, t_k, state, v) writes
// v(state, t_k) into v, where k counts evaluations 0 .. evaluations()-1 in call order and t_k is
// evaluation_times()[k] (so a model can precompute per-evaluation tables, e.g. modulations).
// For Euler k is the step index and t_k the grid point.
#pragma once

#include <array>
#include <cstdint>
#include <type_traits>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona::flow {

// The most state-sized float scratch buffers any rule needs (DPM-Solver++(2M): two x0 predictions).
inline constexpr int max_scratch_states = 2;

// A rule's scratch states, state-sized float32 tensors the caller takes (before a graph capture).
template <class B>
struct SolverScratch {
  std::array<Tensor<float, B>, max_scratch_states> states;
};

// What a rule's step sees: the state, the velocity buffer, its scratch and the grid, and three
// verbs. `evaluate` runs the next velocity evaluation at a state; `add` is x += a·src; `finish`
// is the step's last update of x (fused with the state's conversion when more steps follow).
template <class B, class C, class V, class Velocity>
class StepIO {
 public:
  using Context = BackendContext<B>;
  static constexpr bool kCast = !std::is_same_v<C, float>;

  StepIO(Context& ctx, Tensor<float, B>& x, Tensor<C, B>* xc, Tensor<V, B>& v, SolverScratch<B>& scratch,
         const std::vector<float>& grid, const std::vector<float>& times, Velocity& velocity)
      : ctx_(ctx), x_(x), xc_(xc), v_(v), scratch_(scratch), grid_(grid), times_(times), velocity_(velocity) {}

  Context& ctx() { return ctx_; }
  Tensor<float, B>& x() { return x_; }
  Tensor<V, B>& v() { return v_; }
  Tensor<float, B>& scratch(int j) { return scratch_.states[static_cast<std::size_t>(j)]; }
  std::int64_t steps() const { return static_cast<std::int64_t>(grid_.size()) - 1; }
  float t(std::int64_t i) const { return grid_[static_cast<std::size_t>(i)]; }
  // The fp32 factor of step i: t_{i+1} - t_i formed in double, rounded once (as the official).
  float step_size(std::int64_t i) const { return static_cast<float>(double(t(i + 1)) - double(t(i))); }
  std::int64_t evaluations_done() const { return k_; }

  // Starts the loop: the cast state is made current from x.
  void begin() {
    if constexpr (kCast) convert(ctx_, x_.data(), xc_->data(), x_.numel());
    cast_current_ = true;
  }

  // v = v(state, t_k) for the next evaluation k; state is x or one of the scratch states.
  void evaluate(const Tensor<float, B>& state) {
    EPONA_CHECK(k_ < static_cast<std::int64_t>(times_.size()), "flow solver: evaluation ", k_, " beyond the ",
                times_.size(), " planned (rule and evaluation times disagree)");
    const float t = times_[static_cast<std::size_t>(k_)];
    if constexpr (kCast) {
      const bool at_x = state.data() == x_.data();
      if (!(at_x && cast_current_)) convert(ctx_, state.data(), xc_->data(), state.numel());
      cast_current_ = at_x;
      velocity_(k_, t, static_cast<const Tensor<C, B>&>(*xc_), v_);
    } else {
      velocity_(k_, t, state, v_);
    }
    ++k_;
  }

  // dst += a·src (src the velocity or a float scratch state); x's cast goes stale if dst is x.
  template <class S>
  void add(Tensor<float, B>& dst, const Tensor<S, B>& src, float a) {
    axpy(ctx_, dst.data(), src.data(), a, dst.numel());
    if (dst.data() == x_.data()) cast_current_ = false;
  }
  void copy_state(const Tensor<float, B>& src, Tensor<float, B>& dst) { copy(ctx_, src.data(), dst.data(), src.numel()); }

  // x += a·src as step i's last update of x: when the velocity reads a cast and another step
  // follows, the cast of the new x is written by the same pass (what the Euler sampler did).
  template <class S>
  void finish(std::int64_t i, const Tensor<S, B>& src, float a) {
    if constexpr (kCast) {
      if (i + 1 < steps()) {
        axpy_convert(ctx_, x_.data(), src.data(), a, xc_->data(), x_.numel());
        cast_current_ = true;
        return;
      }
    }
    add(x_, src, a);
  }

 private:
  Context& ctx_;
  Tensor<float, B>& x_;
  Tensor<C, B>* xc_;
  Tensor<V, B>& v_;
  SolverScratch<B>& scratch_;
  const std::vector<float>& grid_;
  const std::vector<float>& times_;
  Velocity& velocity_;
  std::int64_t k_ = 0;
  bool cast_current_ = false;
};

// Rule concept (flow/rules.hpp): name, order (of the global error), scratch_states, and
//   static std::int64_t evaluations(std::int64_t steps)                         — velocity calls of a sample
//   static void times(const std::vector<float>& grid, std::vector<float>& out)  — every evaluation time, in order
//   template <class IO> static void step(IO& io, std::int64_t i)               — one step t_i -> t_{i+1}
template <class B, class Rule>
class FlowSolver {
 public:
  using Context = BackendContext<B>;
  static constexpr int order = Rule::order;
  static constexpr int scratch_states = Rule::scratch_states;
  static_assert(scratch_states <= max_scratch_states, "a rule needs more scratch states than SolverScratch holds");

  explicit FlowSolver(std::vector<float> time_grid) : grid(std::move(time_grid)) {
    EPONA_CHECK(grid.size() >= 2, "a flow solver needs at least 2 grid points, got ", grid.size());
    Rule::times(grid, times_);
    EPONA_CHECK(evaluations() == Rule::evaluations(steps()), Rule::name, ": ", evaluations(),
                " evaluation times for ", steps(), " steps, the rule counts ", Rule::evaluations(steps()));
  }

  std::vector<float> grid;  // t_0 = 0 (noise) .. t_N = 1 (data)

  std::int64_t steps() const { return static_cast<std::int64_t>(grid.size()) - 1; }
  std::int64_t evaluations() const { return static_cast<std::int64_t>(times_.size()); }
  // The time of every velocity evaluation, in call order (t_k of the velocity contract).
  const std::vector<float>& evaluation_times() const { return times_; }
  // The fp32 factor that multiplies v in an Euler step i.
  float step_size(std::int64_t i) const {
    return static_cast<float>(static_cast<double>(grid[i + 1]) - static_cast<double>(grid[i]));
  }

  // Integrates x in place; velocity(k, t_k, x_k, v) reads the float32 state.
  template <class V, class Velocity>
  void sample(Context& ctx, Tensor<float, B>& x, Tensor<V, B>& v, Velocity&& velocity,
              SolverScratch<B> scratch = {}) const {
    run<float>(ctx, x, nullptr, v, velocity, scratch);
  }

  // The same for a velocity that reads its input in another type C (the GPU's bf16 DiTs, whose
  // first GEMM takes the float32 state rounded to bf16): the rounded state lives in xc, made by
  // the step's last update of x in the same pass where it can (Euler: every step), else by a
  // conversion before the evaluation. velocity(k, t_k, xc, v).
  template <class C, class V, class Velocity>
  void sample_cast(Context& ctx, Tensor<float, B>& x, Tensor<C, B>& xc, Tensor<V, B>& v, Velocity&& velocity,
                   SolverScratch<B> scratch = {}) const {
    EPONA_CHECK(x.numel() == xc.numel(), "flow solver: state ", shape_str(x.shape()), " and its cast ",
                shape_str(xc.shape()), " differ in size");
    run<C>(ctx, x, &xc, v, velocity, scratch);
  }

 private:
  template <class C, class V, class Velocity>
  void run(Context& ctx, Tensor<float, B>& x, Tensor<C, B>* xc, Tensor<V, B>& v, Velocity& velocity,
           SolverScratch<B>& scratch) const {
    EPONA_CHECK(x.numel() == v.numel(), Rule::name, ": state ", shape_str(x.shape()), " and velocity ",
                shape_str(v.shape()), " differ in size");
    for (int j = 0; j < scratch_states; ++j)
      EPONA_CHECK(scratch.states[j].numel() == x.numel(), Rule::name, ": scratch state ", j, " has ",
                  scratch.states[j].numel(), " elements, the state ", x.numel());
    StepIO<B, C, V, Velocity> io(ctx, x, xc, v, scratch, grid, times_, velocity);
    io.begin();
    for (std::int64_t i = 0; i < steps(); ++i) Rule::step(io, i);
    EPONA_CHECK(io.evaluations_done() == evaluations(), Rule::name, ": ", io.evaluations_done(),
                " evaluations made, ", evaluations(), " planned");
  }

  std::vector<float> times_;
};

}  // namespace epona::flow
