// apps/epona/cuda_engine.cu — the epona program's CUDA engine: ModelEngine<Cuda, float or bf16>
// (apps/epona/engine.hpp) instantiated by nvcc, so that `--backend cuda` runs the world model and
// the DC-AE on the GPU while the rest of the program is plain C++. Built only with EPONA_CUDA.
#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"

#include "engine.hpp"

namespace epona::app {

std::unique_ptr<Engine> make_cuda_engine(const ComputeOptions& c) {
  EPONA_CHECK(cuda::has_gpu(), "--backend cuda: no CUDA device is available (driver and GPU needed); use --backend cpu");
  if (c.bf16_weights) return std::make_unique<ModelEngine<Cuda, bf16>>(c);
  return std::make_unique<ModelEngine<Cuda, float>>(c);
}

}  // namespace epona::app
