// The flow solvers' loop on the GPU (flow/solver.hpp with every rule of flow/rules.hpp): on
// dx/dt = x (the velocity a device copy of the state), the float32 path gives the CPU solver's
// bits (both backends round a·v and the add apart), and the bf16 path (sample_cast: the state
// converted for a bf16 velocity, the update fused with the conversion where a step ends) stays
// within bf16 rounding of the CPU float32 result. Skips without a GPU.
#include <doctest/doctest.h>

#include <string>

#include "../metrics.hpp"
#include "cuda_test_util.cuh"
#include "epona/cuda/backend.cuh"
#include "epona/flow/schedule.hpp"
#include "epona/flow/solvers.hpp"

using namespace epona;

namespace {

constexpr std::int64_t kN = 1000;  // odd-sized tails are covered by the kernels' own tests

Tensor<float, Cpu> cpu_result(flow::SolverKind kind, const std::vector<float>& grid, const Tensor<float, Cpu>& x0) {
  cpu::Context ctx(1);
  auto x = x0.clone();
  Tensor<float, Cpu> v(x.shape());
  flow::SolverScratch<Cpu> scratch;
  for (auto& s : scratch.states) s = Tensor<float, Cpu>(x.shape());
  flow::with_solver<Cpu>(kind, grid, [&](const auto& solver) {
    solver.sample(ctx, x, v, [&](std::int64_t, float, const Tensor<float, Cpu>& s, Tensor<float, Cpu>& out) {
      std::copy_n(s.data(), s.numel(), out.data());
    }, scratch);
  });
  return x;
}

template <class C>
Tensor<float, Cpu> gpu_result(cuda::Context& ctx, flow::SolverKind kind, const std::vector<float>& grid,
                              const Tensor<float, Cpu>& x0) {
  auto x = test::upload<float>(ctx, x0);
  Tensor<C, Cuda> xc(x0.shape()), v(x0.shape());
  flow::SolverScratch<Cuda> scratch;
  for (auto& s : scratch.states) s = Tensor<float, Cuda>(x0.shape());
  const auto velocity = [&](std::int64_t, float, const auto& s, Tensor<C, Cuda>& out) {
    cuda::copy(ctx, s.data(), out.data(), s.numel());
  };
  flow::with_solver<Cuda>(kind, grid, [&](const auto& solver) {
    if constexpr (std::is_same_v<C, float>)
      solver.sample(ctx, x, v, velocity, scratch);
    else
      solver.sample_cast(ctx, x, xc, v, velocity, scratch);
  });
  return test::download(ctx, x);
}

}  // namespace

TEST_CASE("flow solvers on the GPU: float32 bit for bit with the CPU, bf16 within its rounding") {
  EPONA_REQUIRE_GPU();
  cuda::Context ctx;
  const auto x0 = test::random_tensor({kN}, 7, -2.f, 2.f);
  for (const auto kind : flow::all_solver_kinds)
    for (const std::int64_t steps : {1, 2, 5, 10}) {
      const std::string what = std::string(flow::solver_name(kind)) + " x " + std::to_string(steps);
      const auto grid = flow::get_schedule(steps, 512);
      const auto ref = cpu_result(kind, grid, x0);
      const auto f32 = gpu_result<float>(ctx, kind, grid, x0);
      const auto b16 = gpu_result<bf16>(ctx, kind, grid, x0);
      const auto differ = test::count_bit_differences(f32, ref);
      const double rel = test::rel_max(b16, ref);
      MESSAGE(what, ": float32 values differing from the CPU's ", differ, ", bf16 rel ", rel);
      CHECK(differ == 0);
      CHECK(rel <= 3e-2);
    }
}
