// python/cuda_model.cu — the `epona` Python module's CUDA model: ModelOf<Cuda, float or bf16>
// (python/model_of.hpp) instantiated by nvcc, so that epona.load(backend="cuda") runs the world
// model and the DC-AE on the GPU while the pybind11 code stays plain C++ (no pybind11 or Python
// header here). Built into the module only with EPONA_CUDA and EPONA_PYTHON (python/CMakeLists.txt).
#include <memory>
#include <mutex>

#include "epona/cuda/backend.cuh"
#include "epona/cuda/dcae_ops.cuh"

#include "model_of.hpp"

namespace epona::python {

namespace {

// The cuDNN handles and plans are process-wide: released when the last CUDA model is gone (the
// CLI's one engine releases them with itself, apps/epona/cuda_engine.cuh), not by a static
// destructor that runs after the CUDA context is gone, nor under a model still in use.
struct CudnnRelease {
  ~CudnnRelease() { cuda::release_cudnn(); }
};

std::shared_ptr<void> cudnn_hold() {
  static std::mutex mutex;
  static std::weak_ptr<CudnnRelease> current;
  std::lock_guard lock(mutex);
  std::shared_ptr<CudnnRelease> hold = current.lock();
  if (!hold) current = hold = std::make_shared<CudnnRelease>();
  return hold;
}

}  // namespace

bool cuda_device_present() { return cuda::has_gpu(); }

std::unique_ptr<ModelApi> make_cuda_model(const app::ModelFiles& files, const app::ComputeOptions& c,
                                          const app::Console& con) {
  EPONA_CHECK(cuda::has_gpu(), "backend 'cuda': no CUDA device is available (driver and GPU needed); "
              "use backend='cpu' (epona.cuda_available() tells beforehand)");
  if (c.bf16_weights) return std::make_unique<ModelOf<Cuda, bf16>>(files, c, con, cudnn_hold());
  return std::make_unique<ModelOf<Cuda, float>>(files, c, con, cudnn_hold());
}

}  // namespace epona::python
