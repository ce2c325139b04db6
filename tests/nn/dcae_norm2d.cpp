// Tests for epona/nn/norm2d.hpp (kernels rms_norm_2d / batch_norm_2d of epona/cpu/conv.hpp)
// against float64 loops: RMSNorm2d over channels per pixel with weight and bias (pixel counts
// around the kernel's 256-pixel tile), eval BatchNorm2d from running statistics, the fused
// activation, and the binding rules of BatchNorm buffers (num_batches_tracked accepted as an
// int64 scalar, refused otherwise; missing statistics reported). Tolerance rel <= 1e-6.
#include <doctest/doctest.h>

#include "dcae_reference.hpp"
#include "epona/cpu/context.hpp"
#include "epona/nn/norm2d.hpp"

using namespace epona;
using dcae_ref::HostTensor;
using dcae_ref::i64;

namespace {
io::RawTensor raw(const HostTensor& t) {
  return {DType::F32, t.shape(), {reinterpret_cast<const std::byte*>(t.data()), t.nbytes()}};
}
}  // namespace

TEST_CASE("RMSNorm2d normalises each pixel over its channels, then weight and bias") {
  cpu::Context ctx;
  for (i64 HW : {1, 7, 256, 300, 513}) {
    INFO("HW = " << HW);
    const i64 N = 2, C = 37;
    nn::Norm2d<Cpu, float> norm(nn::Norm2dKind::Rms, C);
    norm.randomize(3);
    HostTensor x = dcae_ref::random_tensor({N, C, 1, HW}, 4, -3.f, 3.f);
    const auto ref = dcae_ref::rms_norm_2d(dcae_ref::to_vec(x), N, C, HW, dcae_ref::to_vec(norm.weight),
                                           dcae_ref::to_vec(norm.bias), 1e-5);
    norm.forward_inplace(ctx, x);
    CHECK(dcae_ref::rel_max(x, ref) <= 1e-6);
  }
}

TEST_CASE("RMSNorm2d with a following ReLU / SiLU, and tiny inputs (eps dominates)") {
  cpu::Context ctx;
  const i64 C = 5, HW = 9;
  nn::Norm2d<Cpu, float> norm(nn::Norm2dKind::Rms, C);
  norm.randomize(5);
  for (ConvAct act : {ConvAct::Relu, ConvAct::Silu}) {
    HostTensor x = dcae_ref::random_tensor({1, C, 3, 3}, 6, -1e-4f, 1e-4f);
    auto ref = dcae_ref::rms_norm_2d(dcae_ref::to_vec(x), 1, C, HW, dcae_ref::to_vec(norm.weight),
                                     dcae_ref::to_vec(norm.bias), 1e-5);
    for (auto& v : ref) v = act == ConvAct::Relu ? dcae_ref::relu(v) : dcae_ref::silu(v);
    norm.forward_inplace(ctx, x, act);
    CHECK(dcae_ref::rel_max(x, ref) <= 1e-6);
  }
}

TEST_CASE("BatchNorm2d (eval) uses the running statistics") {
  cpu::Context ctx;
  const i64 N = 2, C = 6, H = 3, W = 5;
  nn::Norm2d<Cpu, float> bn(nn::Norm2dKind::Batch, C);
  bn.randomize(7);
  HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 8, -2.f, 2.f);
  dcae_ref::Vec ref(static_cast<std::size_t>(x.numel()));
  for (i64 n = 0; n < N; ++n)
    for (i64 c = 0; c < C; ++c)
      for (i64 p = 0; p < H * W; ++p) {
        const i64 i = (n * C + c) * H * W + p;
        ref[i] = (double(x.data()[i]) - bn.running_mean.data()[c]) / std::sqrt(double(bn.running_var.data()[c]) + 1e-5) *
                     bn.weight.data()[c] + bn.bias.data()[c];
      }
  bn.forward_inplace(ctx, x);
  CHECK(dcae_ref::rel_max(x, ref) <= 1e-6);
}

TEST_CASE("BatchNorm2d binding: four float buffers, the int64 counter accepted and checked") {
  const i64 C = 4;
  HostTensor w = dcae_ref::random_tensor({C}, 1), b = dcae_ref::random_tensor({C}, 2),
             m = dcae_ref::random_tensor({C}, 3), v = dcae_ref::random_tensor({C}, 4, 0.5f, 2.f);
  std::int64_t count = 17;
  const io::RawTensor counter{DType::I64, {}, {reinterpret_cast<const std::byte*>(&count), sizeof count}};
  auto make_map = [&](bool with_var, bool float_counter) {
    io::TensorMap map("bn.safetensors");
    map.add("bn.weight", raw(w));
    map.add("bn.bias", raw(b));
    map.add("bn.running_mean", raw(m));
    if (with_var) map.add("bn.running_var", raw(v));
    map.add("bn.num_batches_tracked", float_counter ? raw(w.slice(0, 1).reshape({})) : counter);
    return map;
  };
  {
    const auto map = make_map(true, false);
    nn::Norm2d<Cpu, float> bn(nn::Norm2dKind::Batch, C);
    io::BindReport report(map);
    bn.bind(map, "bn.", report);
    CHECK(report.ok());
    CHECK(bn.running_var.at(2) == v.at(2));
  }
  {
    const auto map = make_map(false, false);
    nn::Norm2d<Cpu, float> bn(nn::Norm2dKind::Batch, C);
    io::BindReport report(map);
    bn.bind(map, "bn.", report);
    CHECK_THROWS_WITH_AS(report.finish(false), doctest::Contains("missing 'bn.running_var'"), Error);
  }
  {
    const auto map = make_map(true, true);
    nn::Norm2d<Cpu, float> bn(nn::Norm2dKind::Batch, C);
    io::BindReport report(map);
    bn.bind(map, "bn.", report);
    CHECK_THROWS_WITH_AS(report.finish(false), doctest::Contains("'bn.num_batches_tracked' should be an int64 scalar"),
                         Error);
  }
  {  // an RMSNorm2d binds only weight and bias: the statistics are unexpected in a strict bind
    const auto map = make_map(true, false);
    nn::Norm2d<Cpu, float> rms(nn::Norm2dKind::Rms, C);
    io::BindReport report(map);
    rms.bind(map, "bn.", report);
    CHECK_THROWS_WITH_AS(report.finish(true), doctest::Contains("unexpected 'bn.running_mean'"), Error);
  }
}

TEST_CASE("Norm2d refuses inputs of the wrong channel count") {
  cpu::Context ctx;
  nn::Norm2d<Cpu, float> norm(nn::Norm2dKind::Rms, 3);
  norm.randomize(1);
  HostTensor x = dcae_ref::random_tensor({1, 4, 2, 2}, 1);
  CHECK_THROWS_WITH_AS(norm.forward_inplace(ctx, x), doctest::Contains("RMSNorm2d(3): input must be (N, 3, H, W)"),
                       Error);
}
