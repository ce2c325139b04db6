// The op sweep (tests/ops/sweep.hpp) on the CPU backend: every op against its float64 reference,
// with float32 and bf16 weights (activations are float32 on the CPU either way, so both run
// under the float32 bounds). Outputs are filled with NaN before each op.
#include <doctest/doctest.h>

#include <cstring>
#include <limits>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/cpu/pixel_shuffle.hpp"
#include "epona/nn/backend_context.hpp"
#include "sweep.hpp"

namespace ops_sweep {

template <> struct Device<epona::Cpu> {
  static constexpr const char* name = "cpu";
  static constexpr bool channels_last = false;  // NCHW maps

  template <class T>
  static epona::Tensor<T, epona::Cpu> upload(epona::cpu::Context&, const std::vector<float>& host) {
    epona::Tensor<T, epona::Cpu> t({static_cast<i64>(host.size())});
    for (std::size_t i = 0; i < host.size(); ++i) t.data()[i] = T(host[i]);
    return t;
  }
  template <class T>
  static epona::Tensor<T, epona::Cpu> output(epona::cpu::Context&, i64 n) {
    epona::Tensor<T, epona::Cpu> t({n});
    for (i64 i = 0; i < n; ++i) t.data()[i] = T(std::numeric_limits<float>::quiet_NaN());
    return t;
  }
  template <class T>
  static std::vector<float> download(epona::cpu::Context&, const epona::Tensor<T, epona::Cpu>& t) {
    std::vector<float> host(static_cast<std::size_t>(t.numel()));
    for (i64 i = 0; i < t.numel(); ++i) host[i] = float(t.data()[i]);
    return host;
  }
};

}  // namespace ops_sweep

TEST_CASE("op sweep: CPU, float32 weights") {
  epona::cpu::Context ctx;
  ops_sweep::sweep<epona::Cpu, float>(ctx);
}

TEST_CASE("op sweep: CPU, bf16 weights") {
  epona::cpu::Context ctx;
  ops_sweep::sweep<epona::Cpu, epona::bf16>(ctx);
}

// The one-backend ops (sweep.hpp): the CPU has its own and none of the GPU's, so the sweep's
// "not on this backend" lines are these and no others.
static_assert(ops_sweep::HasCpuOnlyOps<epona::cpu::Context, float>);
static_assert(!ops_sweep::HasLinearAccumulate<epona::cpu::Context, float> &&
              !epona::GroupedLinear<epona::cpu::Context, float> &&
              !epona::AddGatedNormFromInput<epona::cpu::Context, float> &&
              !epona::QkLayerNormRope<epona::cpu::Context, float> &&
              !epona::JointQkNormRope<epona::cpu::Context, float> &&
              !epona::FusedFrameTokens<epona::cpu::Context, float> &&
              !epona::ShortAttentionQkNorm<epona::cpu::Context, float> &&
              !epona::ItemRowNorms<epona::cpu::Context, float> &&
              !ops_sweep::HasConvert<epona::cpu::Context, float> &&
              !ops_sweep::HasNorm2dAdd<epona::cpu::Context, float> &&
              !ops_sweep::HasRmsNormRows<epona::cpu::Context, float> &&
              !ops_sweep::HasConv2dResidual<epona::cpu::Context, float>);
