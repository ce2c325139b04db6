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

// The one dispatch from a kind to its rule: f(Rule{}) for the rule of `kind`.
template <class F>
decltype(auto) visit_rule(SolverKind kind, F&& f) {
  switch (kind) {
    case SolverKind::heun: return f(HeunRule{});
    case SolverKind::midpoint: return f(MidpointRule{});
    case SolverKind::dpmpp2m: return f(DpmSolverPP2MRule{});
    case SolverKind::euler: break;
  }
  return f(EulerRule{});
}

inline const char* solver_name(SolverKind k) {
  return visit_rule(k, [](auto rule) { return decltype(rule)::name; });
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
  return visit_rule(kind, [&](auto rule) -> decltype(auto) {
    return f(FlowSolver<B, decltype(rule)>(std::move(grid)));
  });
}

// Velocity evaluations of `steps` steps of `kind` (what a sample costs).
inline std::int64_t solver_evaluations(SolverKind kind, std::int64_t steps) {
  return visit_rule(kind, [&](auto rule) { return decltype(rule)::evaluations(steps); });
}

// Scratch states (state-sized float32 buffers) `kind` needs.
inline int solver_scratch_states(SolverKind kind) {
  return visit_rule(kind, [](auto rule) { return decltype(rule)::scratch_states; });
}

// One DiT's sampler: which solver and how many steps (the step count checked by the model).
struct SolverSetting {
  SolverKind kind = SolverKind::euler;
  std::int64_t steps = 100;
  std::int64_t evaluations() const { return solver_evaluations(kind, steps); }
  bool operator==(const SolverSetting&) const = default;
};

}  // namespace epona::flow
