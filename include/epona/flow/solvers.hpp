// epona/flow/solvers.hpp — the solver chosen at run time: a kind (euler, heun, midpoint,
// dpmpp2m) and a step count per DiT, their names for the command line and reports, and one
// dispatch from the kind to the FlowSolver<B, Rule> that runs it. The default is the official
// sampler, 100 Euler steps.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/flow/rules.hpp"
#include "epona/flow/solver.hpp"

namespace epona::flow {

enum class SolverKind { euler, heun, midpoint, dpmpp2m };

inline constexpr std::array<SolverKind, 4> all_solver_kinds = {SolverKind::euler, SolverKind::heun,
                                                               SolverKind::midpoint, SolverKind::dpmpp2m};

inline const char* solver_name(SolverKind k) {
  switch (k) {
    case SolverKind::euler: return EulerRule::name;
    case SolverKind::heun: return HeunRule::name;
    case SolverKind::midpoint: return MidpointRule::name;
    case SolverKind::dpmpp2m: return DpmSolverPP2MRule::name;
  }
  return "?";
}

// "euler|heun|midpoint|dpmpp2m", for help texts and errors.
inline std::string solver_names(const char* separator = "|") {
  std::string s;
  for (auto k : all_solver_kinds) s += (s.empty() ? "" : separator) + std::string(solver_name(k));
  return s;
}

inline SolverKind parse_solver(std::string_view name) {
  for (auto k : all_solver_kinds)
    if (name == solver_name(k)) return k;
  throw Error("unknown solver '" + std::string(name) + "' (one of " + solver_names(", ") + ")");
}

// Runs f(FlowSolver<B, Rule>{grid}) for the rule of `kind`; returns what f returns.
template <class B, class F>
decltype(auto) with_solver(SolverKind kind, std::vector<float> grid, F&& f) {
  switch (kind) {
    case SolverKind::heun: return f(FlowSolver<B, HeunRule>(std::move(grid)));
    case SolverKind::midpoint: return f(FlowSolver<B, MidpointRule>(std::move(grid)));
    case SolverKind::dpmpp2m: return f(FlowSolver<B, DpmSolverPP2MRule>(std::move(grid)));
    case SolverKind::euler: break;
  }
  return f(FlowSolver<B, EulerRule>(std::move(grid)));
}

// Velocity evaluations of `steps` steps of `kind` (what a sample costs).
inline std::int64_t solver_evaluations(SolverKind kind, std::int64_t steps) {
  switch (kind) {
    case SolverKind::heun: return 2 * steps - 1;
    case SolverKind::midpoint: return 2 * steps;
    case SolverKind::euler:
    case SolverKind::dpmpp2m: break;
  }
  return steps;
}

// Scratch states (state-sized float32 buffers) `kind` needs.
inline int solver_scratch_states(SolverKind kind) {
  switch (kind) {
    case SolverKind::heun: return HeunRule::scratch_states;
    case SolverKind::midpoint: return MidpointRule::scratch_states;
    case SolverKind::dpmpp2m: return DpmSolverPP2MRule::scratch_states;
    case SolverKind::euler: break;
  }
  return EulerRule::scratch_states;
}

// One DiT's sampler: which solver and how many steps (the step count checked by the model).
struct SolverSetting {
  SolverKind kind = SolverKind::euler;
  std::int64_t steps = 100;
  std::int64_t evaluations() const { return solver_evaluations(kind, steps); }
  bool operator==(const SolverSetting&) const = default;
};

}  // namespace epona::flow
