// Names of the backend ops' options for test messages, shared by the op sweep (tests/ops) and
// the GPU tests (tests/cuda/cuda_test_util.cuh).
#pragma once

#include "epona/core/kernel_options.hpp"
#include "epona/core/shapes.hpp"

namespace epona::test {

// A GEMM epilogue's name.
inline const char* epilogue_name(Epilogue e) {
  switch (e) {
    case Epilogue::None: return "none";
    case Epilogue::GeluErf: return "gelu_erf";
    case Epilogue::GeluTanh: return "gelu_tanh";
    case Epilogue::Silu: return "silu";
  }
  return "?";
}

// A convolution's fused activation's name.
inline const char* conv_act_name(ConvAct a) {
  return a == ConvAct::None ? "none" : a == ConvAct::Relu ? "relu" : "silu";
}

}  // namespace epona::test
