// epona/flow/euler.hpp — the official sampler (`FluxDiT.sample` / `TrajDiT.sample`): explicit
// Euler integration of dx/dt = v(x, t) over a time grid, x += (t_{i+1} - t_i)·v(x, t_i), the step
// formed in double from the two fp32 grid values and rounded to fp32 where it multiplies v. It is
// the flow solver (flow/solver.hpp) with the Euler rule (flow/rules.hpp). The velocity may be
// stored in bf16 (the GPU's bf16 DiTs): the product a·v is then rounded to bf16 before it is
// added, as PyTorch's `x + dt * v` under autocast; a velocity that reads a bf16 state gets it
// from the update pass itself (sample_cast).
#pragma once

#include "epona/flow/rules.hpp"
#include "epona/flow/solver.hpp"

namespace epona::flow {

template <class B>
using RectifiedFlowEuler = FlowSolver<B, EulerRule>;

}  // namespace epona::flow
