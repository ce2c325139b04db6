// epona/flow/euler.hpp — explicit Euler integration of dx/dt = v(x, t) over a time grid
// (`FluxDiT.sample` / `TrajDiT.sample`): x += (t_{i+1} - t_i)·v(x, t_i), the step formed in
// double from the two fp32 grid values and rounded to fp32 where it multiplies v. Written
// once against any velocity callable; the state (float32) and velocity buffers are the
// caller's. The velocity may be stored in bf16 (the GPU's bf16 DiTs): the product a·v is then
// rounded to bf16 before it is added, as PyTorch's `x + dt * v` under autocast; a velocity
// that reads a bf16 state gets it from the update pass itself (sample_cast).
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona::flow {

template <class B>
struct RectifiedFlowEuler {
  using Context = BackendContext<B>;

  std::vector<float> grid;  // t_0 = 0 (noise) .. t_N = 1 (data)

  explicit RectifiedFlowEuler(std::vector<float> time_grid) : grid(std::move(time_grid)) {
    EPONA_CHECK(grid.size() >= 2, "an Euler sampler needs at least 2 grid points, got ", grid.size());
  }

  std::int64_t steps() const { return static_cast<std::int64_t>(grid.size()) - 1; }

  // The fp32 factor that multiplies v at step i.
  float step_size(std::int64_t i) const {
    return static_cast<float>(static_cast<double>(grid[i + 1]) - static_cast<double>(grid[i]));
  }

  // Integrates x in place. velocity(i, t_i, x, v) must write v(x, t_i) into v (same shape as x).
  template <class V, class Velocity>
  void sample(Context& ctx, Tensor<float, B>& x, Tensor<V, B>& v, Velocity&& velocity) const {
    EPONA_CHECK(x.numel() == v.numel(), "Euler: state ", shape_str(x.shape()), " and velocity ",
                shape_str(v.shape()), " differ in size");
    for (std::int64_t i = 0; i < steps(); ++i) {
      velocity(i, grid[i], static_cast<const Tensor<float, B>&>(x), v);
      axpy(ctx, x.data(), v.data(), step_size(i), x.numel());
    }
  }

  // The same for a velocity that reads its input in another type C (the GPU's bf16 DiTs, whose
  // first GEMM takes the float32 state rounded to bf16): the state is also kept rounded in xc,
  // converted once before the first step and then by each step's update in the same pass
  // (axpy_convert), so no step converts it apart. velocity(i, t_i, xc, v).
  template <class C, class V, class Velocity>
  void sample_cast(Context& ctx, Tensor<float, B>& x, Tensor<C, B>& xc, Tensor<V, B>& v, Velocity&& velocity) const {
    EPONA_CHECK(x.numel() == v.numel() && x.numel() == xc.numel(), "Euler: state ", shape_str(x.shape()),
                ", its cast ", shape_str(xc.shape()), " and velocity ", shape_str(v.shape()), " differ in size");
    convert(ctx, x.data(), xc.data(), x.numel());
    for (std::int64_t i = 0; i < steps(); ++i) {
      velocity(i, grid[i], static_cast<const Tensor<C, B>&>(xc), v);
      if (i + 1 < steps())
        axpy_convert(ctx, x.data(), v.data(), step_size(i), xc.data(), x.numel());
      else
        axpy(ctx, x.data(), v.data(), step_size(i), x.numel());
    }
  }
};

}  // namespace epona::flow
