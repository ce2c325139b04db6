// epona/flow/rules.hpp — the update rules of the rectified-flow solver (flow/solver.hpp): Euler
// (the official sampler, 1 evaluation a step), Heun (explicit trapezoid, 2nd order, 2 a step but
// the last), midpoint (2nd order, 2 a step) and DPM-Solver++(2M) in its flow-matching form
// (2nd order multistep on the data prediction, 1 a step). Time runs from t = 0 (noise) to 1
// (data); in the diffusers/SANA notation sigma = 1 - t, alpha = t, lambda = log(t / (1 - t)).
// Every update is written as x += a·(something) so the same two backend ops (copy, axpy) serve
// every rule on every backend, and Euler stays the exact official arithmetic.
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

namespace epona::flow {

// x_{i+1} = x_i + (t_{i+1} - t_i)·v(x_i, t_i): FluxDiT.sample / TrajDiT.sample.
struct EulerRule {
  static constexpr const char* name = "euler";
  static constexpr int order = 1, scratch_states = 0;
  static constexpr std::int64_t evaluations(std::int64_t steps) { return steps; }
  static void times(const std::vector<float>& grid, std::vector<float>& out) {
    out.assign(grid.begin(), grid.end() - 1);  // t_0 .. t_{N-1}: never t = 1
  }
  template <class IO>
  static void step(IO& io, std::int64_t i) {
    io.evaluate(io.x());
    io.finish(i, io.v(), io.step_size(i));
  }
};

// Heun (EDM's 2nd-order sampler): predictor x~ = x + h·v1, corrector x + h/2·(v1 + v(x~, t_{i+1})).
// The last step is an Euler step, as in EDM: its corrector would evaluate at t = 1 exactly, a
// time the official sampler never asks the model about; 2N - 1 evaluations for N steps. That
// step's local error is O(h^2), so the global order stays 2.
struct HeunRule {
  static constexpr const char* name = "heun";
  static constexpr int order = 2, scratch_states = 1;  // the predictor state
  static constexpr std::int64_t evaluations(std::int64_t steps) { return 2 * steps - 1; }
  static void times(const std::vector<float>& grid, std::vector<float>& out) {
    out.clear();
    const std::size_t n = grid.size() - 1;
    for (std::size_t i = 0; i < n; ++i) {
      out.push_back(grid[i]);
      if (i + 1 < n) out.push_back(grid[i + 1]);
    }
  }
  template <class IO>
  static void step(IO& io, std::int64_t i) {
    const float h = io.step_size(i);
    io.evaluate(io.x());
    if (i + 1 == io.steps()) return io.finish(i, io.v(), h);
    auto& predictor = io.scratch(0);
    io.copy_state(io.x(), predictor);
    io.add(predictor, io.v(), h);
    const float half = static_cast<float>(0.5 * (double(io.t(i + 1)) - double(io.t(i))));
    io.add(io.x(), io.v(), half);
    io.evaluate(predictor);
    io.finish(i, io.v(), half);
  }
};

// Explicit midpoint: x + h·v(x + h/2·v1, t_i + h/2); 2N evaluations, none at t = 1.
struct MidpointRule {
  static constexpr const char* name = "midpoint";
  static constexpr int order = 2, scratch_states = 1;  // the midpoint state
  static constexpr std::int64_t evaluations(std::int64_t steps) { return 2 * steps; }
  static float midpoint(const std::vector<float>& grid, std::size_t i) {
    return static_cast<float>(0.5 * (double(grid[i]) + double(grid[i + 1])));
  }
  static void times(const std::vector<float>& grid, std::vector<float>& out) {
    out.clear();
    for (std::size_t i = 0; i + 1 < grid.size(); ++i) {
      out.push_back(grid[i]);
      out.push_back(midpoint(grid, i));
    }
  }
  template <class IO>
  static void step(IO& io, std::int64_t i) {
    io.evaluate(io.x());
    auto& mid = io.scratch(0);
    io.copy_state(io.x(), mid);
    io.add(mid, io.v(), static_cast<float>(0.5 * (double(io.t(i + 1)) - double(io.t(i)))));
    io.evaluate(mid);
    io.finish(i, io.v(), io.step_size(i));
  }
};

// DPM-Solver++(2M) for flow matching (diffusers DPMSolverMultistepScheduler with flow sigmas,
// algorithm_type "dpmsolver++", solver_type "midpoint"). With the data prediction
// m = x + (1 - t)·v and h = lambda(t_{i+1}) - lambda(t_i), r = (lambda(t_i) - lambda(t_{i-1})) / h:
//   x_{i+1} = (sigma'/sigma)·x + alpha'(1 - e^-h)·m_i + 0.5·alpha'(1 - e^-h)/r·(m_i - m_{i-1}).
// Its first-order part equals the Euler step exactly (algebra, shown in docs/solvers.md), so a
// step is Euler plus k·(m_i - m_{i-1}), k = 0.5·alpha'(1 - e^-h)/r. First order where the
// correction is undefined: the first step (no m_{i-1}), the second (m_0 at t = 0, lambda = -inf,
// gives r = inf) and the last (t = 1, lambda = +inf; diffusers' final_sigmas_type "zero" also
// steps first order there). N evaluations.
struct DpmSolverPP2MRule {
  static constexpr const char* name = "dpmpp2m";
  static constexpr int order = 2, scratch_states = 2;  // m_i and m_{i-1}, alternating
  static constexpr std::int64_t evaluations(std::int64_t steps) { return steps; }
  static void times(const std::vector<float>& grid, std::vector<float>& out) { EulerRule::times(grid, out); }

  static double lambda(double t) { return std::log(t) - std::log1p(-t); }
  // The correction's factor k at step i, 0 where the step is first order.
  static double correction(double t_prev, double t, double t_next) {
    if (!(t_prev > 0.0) || !(t_next < 1.0) || !(t > t_prev) || !(t_next > t)) return 0.0;
    const double h = lambda(t_next) - lambda(t), r = (lambda(t) - lambda(t_prev)) / h;
    return 0.5 * t_next * -std::expm1(-h) / r;
  }
  template <class IO>
  static void step(IO& io, std::int64_t i) {
    io.evaluate(io.x());
    auto& m = io.scratch(static_cast<int>(i % 2));            // m_i
    auto& m_prev = io.scratch(static_cast<int>((i + 1) % 2));  // m_{i-1}
    const double k = i > 0 ? correction(io.t(i - 1), io.t(i), io.t(i + 1)) : 0.0;
    if (k == 0.0 && i + 1 == io.steps()) return io.finish(i, io.v(), io.step_size(i));
    io.copy_state(io.x(), m);
    io.add(m, io.v(), static_cast<float>(1.0 - double(io.t(i))));
    if (k == 0.0) return io.finish(i, io.v(), io.step_size(i));
    io.add(io.x(), io.v(), io.step_size(i));
    io.add(io.x(), m, static_cast<float>(k));
    io.finish(i, m_prev, static_cast<float>(-k));
  }
};

}  // namespace epona::flow
