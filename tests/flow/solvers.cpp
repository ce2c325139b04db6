// The flow solvers (flow/solver.hpp, flow/rules.hpp, flow/solvers.hpp) on smooth ODEs with a
// closed form, on the official shifted grid:
// - each rule matches an independent float64 implementation of its textbook formula (the
//   DPM-Solver++(2M) reference is the diffusers form in lambda, sigma and alpha, not the
//   Euler-plus-correction form the engine uses);
// - each shows its order: halving the step divides the error by about 2^order;
// - the velocity contract: evaluations k = 0, 1, .. in order at evaluation_times()[k], as many
//   as solver_evaluations() says; names parse back; bad buffers are refused.
#include <doctest/doctest.h>

#include <cmath>
#include <functional>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"

using namespace epona;

namespace {

// The test ODE, one independent equation per component:
// - components 0..2: the rectified flow from N(0, 1) noise to N(mu, s^2) data, whose velocity is
//   linear in x: v = mu + (t s^2 - (1 - t)) / sigma_t^2 · (x - t mu), sigma_t^2 = t^2 s^2 + (1-t)^2;
//   solution x(t) = t mu + sigma_t x(0);
// - component 3: dx/dt = -x^3, x(t) = x0 / sqrt(1 + 2 x0^2 t) (nonlinear).
struct TestOde {
  static constexpr int n = 4;
  double mu[3] = {1.5, -0.7, 0.3}, s[3] = {0.5, 1.3, 0.8};
  double x0[n] = {0.8, -1.1, 0.4, 1.2};

  double velocity(int j, double x, double t) const {
    if (j == 3) return -x * x * x;
    const double var = t * t * s[j] * s[j] + (1 - t) * (1 - t);
    return mu[j] + (t * s[j] * s[j] - (1 - t)) / var * (x - t * mu[j]);
  }
  double exact(int j, double t) const {
    if (j == 3) return x0[3] / std::sqrt(1 + 2 * x0[3] * x0[3] * t);
    return t * mu[j] + std::sqrt(t * t * s[j] * s[j] + (1 - t) * (1 - t)) * x0[j];
  }
};

// ---- float64 references of each rule, written from the textbook formulas ----
using Field = std::function<double(int, double, double)>;  // (component, x, t)

std::vector<double> ref_euler(const std::vector<float>& g, const Field& f, std::vector<double> x) {
  for (std::size_t i = 0; i + 1 < g.size(); ++i)
    for (std::size_t j = 0; j < x.size(); ++j) x[j] += (double(g[i + 1]) - g[i]) * f(int(j), x[j], g[i]);
  return x;
}

std::vector<double> ref_heun(const std::vector<float>& g, const Field& f, std::vector<double> x) {
  const std::size_t n = g.size() - 1;
  for (std::size_t i = 0; i < n; ++i)
    for (std::size_t j = 0; j < x.size(); ++j) {
      const double h = double(g[i + 1]) - g[i], v1 = f(int(j), x[j], g[i]);
      if (i + 1 == n) {  // EDM: the last step is Euler
        x[j] += h * v1;
        continue;
      }
      const double v2 = f(int(j), x[j] + h * v1, g[i + 1]);
      x[j] += h / 2 * (v1 + v2);
    }
  return x;
}

std::vector<double> ref_midpoint(const std::vector<float>& g, const Field& f, std::vector<double> x) {
  for (std::size_t i = 0; i + 1 < g.size(); ++i)
    for (std::size_t j = 0; j < x.size(); ++j) {
      const double h = double(g[i + 1]) - g[i], tm = float(0.5 * (double(g[i]) + g[i + 1]));
      x[j] += h * f(int(j), x[j] + h / 2 * f(int(j), x[j], g[i]), tm);
    }
  return x;
}

// diffusers' multistep_dpm_solver_second_order_update (dpmsolver++, midpoint) with flow sigmas:
// sigma = 1 - t, alpha = t; first order at the first step, where the previous lambda is -inf
// (r = inf: D1 = 0) and at the final step (sigma = 0).
std::vector<double> ref_dpmpp2m(const std::vector<float>& g, const Field& f, std::vector<double> x) {
  const std::size_t n = g.size() - 1;
  std::vector<double> m_prev(x.size());
  for (std::size_t i = 0; i < n; ++i) {
    const double s0 = 1 - double(g[i]), a0 = g[i], st = 1 - double(g[i + 1]), at = g[i + 1];
    const double exp_neg_h = (a0 * st) / (s0 * at);  // e^{-h}, h = lambda_t - lambda_s0
    const bool second = i > 0 && g[i - 1] > 0 && st > 0;
    for (std::size_t j = 0; j < x.size(); ++j) {
      const double m0 = x[j] + s0 * f(int(j), x[j], g[i]);
      double next = (st / s0) * x[j] - at * (exp_neg_h - 1) * m0;
      if (second) {
        auto L = [](double t) { return std::log(t / (1 - t)); };
        const double h = L(g[i + 1]) - L(g[i]), h0 = L(g[i]) - L(g[i - 1]), r0 = h0 / h;
        const double d1 = (m0 - m_prev[j]) / r0;
        next -= 0.5 * at * (exp_neg_h - 1) * d1;
      }
      m_prev[j] = m0;
      x[j] = next;
    }
  }
  return x;
}

std::vector<double> reference(flow::SolverKind k, const std::vector<float>& g, const Field& f,
                              const std::vector<double>& x) {
  switch (k) {
    case flow::SolverKind::euler: return ref_euler(g, f, x);
    case flow::SolverKind::heun: return ref_heun(g, f, x);
    case flow::SolverKind::midpoint: return ref_midpoint(g, f, x);
    case flow::SolverKind::dpmpp2m: return ref_dpmpp2m(g, f, x);
  }
  return {};
}

// The engine's solver (fp32 state) on the test ODE; also records the evaluation calls.
struct Run {
  std::vector<float> x;
  std::vector<std::int64_t> ks;
  std::vector<float> ts;
  std::vector<float> planned;
};

Run run_engine(flow::SolverKind kind, const std::vector<float>& grid, const TestOde& ode) {
  cpu::Context ctx(1);
  Tensor<float, Cpu> x({TestOde::n}), v({TestOde::n});
  for (int j = 0; j < TestOde::n; ++j) x.data()[j] = float(ode.exact(j, grid.front()));
  flow::SolverScratch<Cpu> scratch;
  for (auto& s : scratch.states) s = Tensor<float, Cpu>({TestOde::n});
  Run r;
  flow::with_solver<Cpu>(kind, grid, [&](const auto& solver) {
    r.planned = solver.evaluation_times();
    solver.sample(
        ctx, x, v,
        [&](std::int64_t k, float t, const Tensor<float, Cpu>& state, Tensor<float, Cpu>& out) {
          r.ks.push_back(k), r.ts.push_back(t);
          for (int j = 0; j < TestOde::n; ++j) out.data()[j] = float(ode.velocity(j, state.data()[j], t));
        },
        scratch);
  });
  r.x.assign(x.data(), x.data() + TestOde::n);
  return r;
}

// Largest error at the grid's end, the solver started from the exact state at its start.
double solver_error(flow::SolverKind kind, const std::vector<float>& grid, const TestOde& ode) {
  const auto x = run_engine(kind, grid, ode).x;
  double e = 0;
  for (int j = 0; j < TestOde::n; ++j) e = std::max(e, std::abs(double(x[j]) - ode.exact(j, grid.back())));
  return e;
}

// Observed orders log2(e(N) / e(2N)) for N = 8, 16, 32 on grids made by `grid_of(steps)`.
std::vector<double> observed_orders(flow::SolverKind kind, const std::function<std::vector<float>(std::int64_t)>& grid_of,
                                    const TestOde& ode, std::vector<double>* errors = nullptr) {
  std::vector<double> err, orders;
  for (const std::int64_t steps : {8, 16, 32, 64}) err.push_back(solver_error(kind, grid_of(steps), ode));
  for (std::size_t i = 1; i < err.size(); ++i) {
    orders.push_back(std::log2(err[i - 1] / err[i]));
    MESSAGE(std::string(flow::solver_name(kind)), " steps ", 8 << i, ": error ", err[i], ", observed order ", orders.back());
  }
  if (errors) *errors = err;
  return orders;
}

// t uniform in [0.1, 0.9]: away from lambda's infinities at t = 0 and 1.
std::vector<float> interior_grid(std::int64_t steps) {
  std::vector<float> g;
  for (std::int64_t i = 0; i <= steps; ++i) g.push_back(float(0.1 + 0.8 * double(i) / double(steps)));
  return g;
}

}  // namespace

TEST_CASE("every rule matches its float64 reference and keeps the velocity contract") {
  const TestOde ode;
  const Field f = [&](int j, double x, double t) { return ode.velocity(j, x, t); };
  const std::vector<double> x0(ode.x0, ode.x0 + TestOde::n);
  for (const auto kind : flow::all_solver_kinds)
    for (const std::int64_t steps : {1, 2, 3, 5, 10, 25}) {
      CAPTURE(flow::solver_name(kind));
      CAPTURE(steps);
      const auto grid = flow::get_schedule(steps, 256);
      const Run r = run_engine(kind, grid, ode);
      REQUIRE(std::int64_t(r.ks.size()) == flow::solver_evaluations(kind, steps));
      REQUIRE(r.planned.size() == r.ks.size());
      for (std::size_t k = 0; k < r.ks.size(); ++k) {
        CHECK(r.ks[k] == std::int64_t(k));
        CHECK(r.ts[k] == r.planned[k]);
        CHECK(r.ts[k] < 1.0f);  // no rule asks the model about t = 1
      }
      const auto ref = reference(kind, grid, f, x0);
      for (int j = 0; j < TestOde::n; ++j) CHECK(r.x[j] == doctest::Approx(ref[j]).epsilon(2e-5).scale(1.0));
    }
}

// Orders are log2 of the error ratio when the step is halved: about 1 (Euler) or 2 (the others).
TEST_CASE("each solver shows its order of accuracy when the step is halved") {
  const TestOde ode;
  SUBCASE("on the official shifted grid, t = 0 -> 1") {
    const auto official = [](std::int64_t steps) { return flow::get_schedule(steps, 256); };
    std::vector<double> euler_err;
    for (double o : observed_orders(flow::SolverKind::euler, official, ode, &euler_err)) CHECK(o == doctest::Approx(1).epsilon(0.25));
    for (const auto kind : {flow::SolverKind::heun, flow::SolverKind::midpoint})
      for (double o : observed_orders(kind, official, ode)) CHECK(o == doctest::Approx(2).epsilon(0.125));
    // DPM-Solver++(2M) from pure noise: its correction extrapolates the data prediction linearly
    // in lambda = log(t/(1-t)), whose steps near t = 0 do not shrink with the grid (log((i+1)/i)),
    // so its asymptotic order there falls towards 1 (as diffusers' on a flow grid from sigma = 1);
    // what it must show is more than first order and a far smaller error than Euler's.
    std::vector<double> dpm_err;
    for (double o : observed_orders(flow::SolverKind::dpmpp2m, official, ode, &dpm_err)) CHECK(o >= 1.1);
    for (std::size_t i = 0; i < dpm_err.size(); ++i) CHECK(dpm_err[i] * 4 < euler_err[i]);
  }
  SUBCASE("on an interior grid, t = 0.1 -> 0.9, every rule at its full order") {
    for (const auto kind : flow::all_solver_kinds) {
      const double order = kind == flow::SolverKind::euler ? 1 : 2;
      // multistep: its first step is first order, so the coarsest ratio is not yet asymptotic
      const auto orders = observed_orders(kind, interior_grid, ode);
      for (double o : orders) CHECK(o >= order - 0.65);
      CHECK(orders.back() == doctest::Approx(order).epsilon(0.125));
    }
  }
}

TEST_CASE("solver names, counts and refusals") {
  for (const auto kind : flow::all_solver_kinds) CHECK(flow::parse_solver(flow::solver_name(kind)) == kind);
  CHECK_THROWS_WITH_AS(flow::parse_solver("rk4"), doctest::Contains("unknown solver 'rk4' (one of euler, heun"), Error);
  CHECK(flow::solver_evaluations(flow::SolverKind::heun, 10) == 19);
  CHECK(flow::solver_evaluations(flow::SolverKind::midpoint, 10) == 20);
  CHECK(flow::solver_evaluations(flow::SolverKind::dpmpp2m, 10) == 10);
  CHECK(flow::solver_scratch_states(flow::SolverKind::dpmpp2m) == 2);

  cpu::Context ctx(1);
  const flow::FlowSolver<Cpu, flow::HeunRule> heun(flow::get_schedule(4, 15));
  Tensor<float, Cpu> x({4}), v({4});
  // Heun without its predictor buffer: refused, naming the rule
  CHECK_THROWS_WITH_AS(heun.sample(ctx, x, v, [](auto, auto, const auto&, auto&) {}),
                       doctest::Contains("heun: scratch state 0"), Error);
}
