// apps/epona/cuda_engine.cu — the epona program's CUDA engine: ModelEngine<Cuda, float or bf16>
// (apps/epona/engine.hpp) instantiated by nvcc, so that `--backend cuda` runs the world model and
// the DC-AE on the GPU while the rest of the program is plain C++. Built only with EPONA_CUDA.
#include "cuda_engine.cuh"

namespace epona::app {

std::unique_ptr<Engine> make_cuda_engine(const ComputeOptions& c) { return build_cuda_engine(c); }

}  // namespace epona::app
