// apps/epona/cuda_engine.cuh — builds the epona program's CUDA engine, ModelEngine<Cuda, float or
// bf16> (apps/epona/engine.hpp); included by cuda_engine.cu (the program's only nvcc unit) and by
// the GPU test of the engine, so both run the same construction.
#pragma once

#include <cstdlib>
#include <memory>

#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"

#include "engine.hpp"

namespace epona::app {

namespace cuda_engine_detail {
// The cuDNN handles and plans are process-wide; released with the engine, not by a static
// destructor that runs after the CUDA context is gone (compute-sanitizer reported them leaked).
// --reproducible: no timed cuBLASLt candidates (which one wins can differ between runs) unless
// EPONA_CUDA_GEMM_TUNE asks for them.
template <class W>
std::unique_ptr<Engine> build(const ComputeOptions& c) {
  auto engine = std::make_unique<ModelEngine<Cuda, W>>(c);
  engine->after_destruction(cuda::release_cudnn);
  if (c.reproducible && !std::getenv("EPONA_CUDA_GEMM_TUNE"))
    engine->configure_contexts([](cuda::Context& ctx) { ctx.policy().gemm_tuning = cuda::GemmTuning::Off; });
  return engine;
}
}  // namespace cuda_engine_detail

inline std::unique_ptr<Engine> build_cuda_engine(const ComputeOptions& c) {
  EPONA_CHECK(cuda::has_gpu(), "--backend cuda: no CUDA device is available (driver and GPU needed); use --backend cpu");
  return c.bf16_weights ? cuda_engine_detail::build<bf16>(c) : cuda_engine_detail::build<float>(c);
}

}  // namespace epona::app
