// epona/cuda/conv_cudnn.cuh — the cuDNN engine of the GPU convolutions: channels-last (NHWC)
// forward convolutions through cuDNN 9's convolution API, loaded at run time (dlopen), so
// nothing links against cuDNN and a machine without it falls back to the GEMM engine. float32
// uses FMA math only (never TF32); bf16 uses tensor cores with float32 accumulation.
#pragma once

#if __has_include(<cudnn.h>)
#include <cudnn.h>
#define EPONA_CUDNN_HEADERS 1
#else
#define EPONA_CUDNN_HEADERS 0
#endif

#include <dlfcn.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstdlib>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <type_traits>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/cpu/conv.hpp"
#include "epona/cuda/context.hpp"
#include "epona/cuda/scratch.hpp"

namespace epona::cuda::cudnn {

#if EPONA_CUDNN_HEADERS

// The cuDNN entry points this engine calls, resolved from the shared library.
#define EPONA_CUDNN_FUNCTIONS(X)                                                                        \
  X(cudnnGetVersion) X(cudnnGetErrorString) X(cudnnCreate) X(cudnnDestroy) X(cudnnSetStream)             \
  X(cudnnCreateTensorDescriptor) X(cudnnDestroyTensorDescriptor) X(cudnnSetTensor4dDescriptor)           \
  X(cudnnCreateFilterDescriptor) X(cudnnDestroyFilterDescriptor) X(cudnnSetFilter4dDescriptor)           \
  X(cudnnCreateConvolutionDescriptor) X(cudnnDestroyConvolutionDescriptor)                                \
  X(cudnnSetConvolution2dDescriptor) X(cudnnSetConvolutionMathType) X(cudnnSetConvolutionGroupCount)      \
  X(cudnnGetConvolutionForwardAlgorithmMaxCount) X(cudnnGetConvolutionForwardAlgorithm_v7)               \
  X(cudnnGetConvolutionForwardWorkspaceSize) X(cudnnConvolutionForward)

struct Api {
#define EPONA_CUDNN_POINTER(name) decltype(&::name) name = nullptr;
  EPONA_CUDNN_FUNCTIONS(EPONA_CUDNN_POINTER)
#undef EPONA_CUDNN_POINTER
  std::size_t version = 0;
  std::string unavailable;  // why cuDNN cannot be used here (empty when it can)

  bool ok() const { return unavailable.empty(); }

  // Loaded once per process: EPONA_CUDNN_LIBRARY names the file, else libcudnn.so.9 from the
  // loader's search path (LD_LIBRARY_PATH, the cache). The library is never unloaded.
  static const Api& get() {
    static const Api api = load();
    return api;
  }

 private:
  static Api load() {
    Api a;
    const char* env = std::getenv("EPONA_CUDNN_LIBRARY");
    void* lib = nullptr;
    std::string tried;
    for (const char* name : {env && *env ? env : "libcudnn.so.9", "libcudnn.so"}) {
      lib = dlopen(name, RTLD_NOW | RTLD_LOCAL);
      if (lib) break;
      const char* err = dlerror();
      tried += std::string(tried.empty() ? "" : "; ") + (err ? err : name);
    }
    if (!lib) {
      a.unavailable = "cannot load cuDNN (" + tried + ")";
      return a;
    }
#define EPONA_CUDNN_RESOLVE(name)                                                     \
  a.name = reinterpret_cast<decltype(&::name)>(dlsym(lib, #name));                    \
  if (!a.name && a.unavailable.empty()) a.unavailable = "cuDNN lacks " #name;
    EPONA_CUDNN_FUNCTIONS(EPONA_CUDNN_RESOLVE)
#undef EPONA_CUDNN_RESOLVE
    if (!a.ok()) return a;
    a.version = a.cudnnGetVersion();
    if (a.version < 90000 || a.version >= 100000)
      a.unavailable = "cuDNN " + std::to_string(a.version) + " is not version 9 (built against " +
                      std::to_string(CUDNN_VERSION) + ")";
    return a;
  }
};

inline void check(cudnnStatus_t status, const char* expr) {
  if (status == CUDNN_STATUS_SUCCESS) return;
  fail("cuDNN error ", Api::get().cudnnGetErrorString(status), " (", static_cast<int>(status), ") in ", expr);
}
#define EPONA_CUDNN_CHECK(expr) ::epona::cuda::cudnn::check((expr), #expr)

// One convolution geometry: descriptors and the algorithm chosen for it (or why none fits).
struct Plan {
  cudnnTensorDescriptor_t x = nullptr, y = nullptr;
  cudnnFilterDescriptor_t w = nullptr;
  cudnnConvolutionDescriptor_t conv = nullptr;
  cudnnConvolutionFwdAlgo_t algo{};
  std::size_t workspace = 0;
  std::string unusable;  // empty when the plan can run

  Plan() = default;
  Plan(const Plan&) = delete;
  Plan& operator=(const Plan&) = delete;
  ~Plan() {  // destructors must not throw: statuses at teardown are not reported
    const Api& api = Api::get();
    if (conv) api.cudnnDestroyConvolutionDescriptor(conv);
    if (w) api.cudnnDestroyFilterDescriptor(w);
    if (y) api.cudnnDestroyTensorDescriptor(y);
    if (x) api.cudnnDestroyTensorDescriptor(x);
  }
};

// Algorithms that compute the plain sum of products (no Winograd or FFT transforms, whose
// rounding differs from the reference's).
inline bool exact_algorithm(cudnnConvolutionFwdAlgo_t a) {
  return a == CUDNN_CONVOLUTION_FWD_ALGO_IMPLICIT_GEMM || a == CUDNN_CONVOLUTION_FWD_ALGO_IMPLICIT_PRECOMP_GEMM ||
         a == CUDNN_CONVOLUTION_FWD_ALGO_GEMM;
}

inline constexpr std::size_t kMaxWorkspace = std::size_t{1} << 30;

// The process-wide engine state: one cuDNN handle per device and the plans made so far.
class Engine {
 public:
  static Engine& get() {
    static Engine e;
    return e;
  }
  Engine(const Engine&) = delete;
  Engine& operator=(const Engine&) = delete;
  ~Engine() { release(); }

  // Destroys every plan and handle (made again on demand).
  void release() {
    std::lock_guard<std::mutex> lock(mutex_);
    plans_.clear();
    for (auto& [device, h] : handles_)
      if (h) Api::get().cudnnDestroy(h);
    handles_.clear();
    reasons_.clear();
  }

  // Why cuDNN cannot run on ctx's device (empty when it can).
  std::string unavailable(Context& ctx) {
    std::lock_guard<std::mutex> lock(mutex_);
    return handle_or_reason(ctx).second;
  }

  // y = conv(x) (no bias) with NHWC x/y and [O, k, k, C/g] w; false when cuDNN or this
  // geometry is unavailable (the caller then uses another engine). Failures after planning throw.
  template <class T>
  bool forward(Context& ctx, const T* x, const T* w, T* y, const Conv2dShape& s) {
    std::lock_guard<std::mutex> lock(mutex_);
    const cudnnHandle_t handle = handle_or_reason(ctx).first;
    if (!handle) return false;
    const Plan& plan = plan_for<T>(ctx, handle, s);
    if (!plan.unusable.empty()) return false;
    const Api& api = Api::get();
    EPONA_CUDNN_CHECK(api.cudnnSetStream(handle, ctx.stream()));
    Tensor<unsigned char, Cuda> workspace;
    if (plan.workspace) workspace = scratch_tensor<unsigned char>(ctx, {static_cast<std::int64_t>(plan.workspace)});
    const float alpha = 1.0f, beta = 0.0f;
    EPONA_CUDNN_CHECK(api.cudnnConvolutionForward(handle, &alpha, plan.x, x, plan.w, w, plan.conv, plan.algo,
                                                  workspace.data(), plan.workspace, &beta, plan.y, y));
    return true;
  }

  // Why a geometry has no cuDNN plan (empty when it has one); for reports.
  template <class T>
  std::string plan_problem(Context& ctx, const Conv2dShape& s) {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto [handle, why] = handle_or_reason(ctx);
    if (!handle) return why;
    return plan_for<T>(ctx, handle, s).unusable;
  }

 private:
  Engine() = default;

  std::pair<cudnnHandle_t, std::string> handle_or_reason(Context& ctx) {
    const Api& api = Api::get();
    if (!api.ok()) return {nullptr, api.unavailable};
    const int device = ctx.info().device;
    auto it = handles_.find(device);
    if (it == handles_.end()) {
      cudnnHandle_t h = nullptr;
      const cudnnStatus_t status = api.cudnnCreate(&h);
      if (status != CUDNN_STATUS_SUCCESS) {
        reasons_[device] = std::string("cudnnCreate failed: ") + api.cudnnGetErrorString(status);
        h = nullptr;
      }
      it = handles_.emplace(device, h).first;
    }
    return {it->second, it->second ? std::string() : reasons_[device]};
  }

  template <class T>
  const Plan& plan_for(Context& ctx, cudnnHandle_t handle, const Conv2dShape& s) {
    const std::array<std::int64_t, 9> key{ctx.info().device, std::is_same_v<T, float> ? 0 : 1, s.batch,
                                          s.in_channels, s.height, s.width, s.out_channels, s.kernel, s.groups};
    auto& plan = plans_[key];
    if (!plan) plan = make_plan<T>(handle, s);
    return *plan;
  }

  template <class T>
  static std::unique_ptr<Plan> make_plan(cudnnHandle_t handle, const Conv2dShape& s) {
    const Api& api = Api::get();
    auto p = std::make_unique<Plan>();
    constexpr bool fp32 = std::is_same_v<T, float>;
    const cudnnDataType_t type = fp32 ? CUDNN_DATA_FLOAT : CUDNN_DATA_BFLOAT16;
    const auto i32 = [](std::int64_t v) { return static_cast<int>(v); };
    const int pad = i32(s.kernel / 2);
    EPONA_CUDNN_CHECK(api.cudnnCreateTensorDescriptor(&p->x));
    EPONA_CUDNN_CHECK(api.cudnnCreateTensorDescriptor(&p->y));
    EPONA_CUDNN_CHECK(api.cudnnCreateFilterDescriptor(&p->w));
    EPONA_CUDNN_CHECK(api.cudnnCreateConvolutionDescriptor(&p->conv));
    EPONA_CUDNN_CHECK(api.cudnnSetTensor4dDescriptor(p->x, CUDNN_TENSOR_NHWC, type, i32(s.batch), i32(s.in_channels),
                                                     i32(s.height), i32(s.width)));
    EPONA_CUDNN_CHECK(api.cudnnSetTensor4dDescriptor(p->y, CUDNN_TENSOR_NHWC, type, i32(s.batch), i32(s.out_channels),
                                                     i32(s.height), i32(s.width)));
    EPONA_CUDNN_CHECK(api.cudnnSetFilter4dDescriptor(p->w, type, CUDNN_TENSOR_NHWC, i32(s.out_channels),
                                                     i32(s.in_channels / s.groups), i32(s.kernel), i32(s.kernel)));
    EPONA_CUDNN_CHECK(api.cudnnSetConvolution2dDescriptor(p->conv, pad, pad, 1, 1, 1, 1, CUDNN_CROSS_CORRELATION,
                                                          CUDNN_DATA_FLOAT));
    EPONA_CUDNN_CHECK(api.cudnnSetConvolutionGroupCount(p->conv, i32(s.groups)));
    // float32: FMA units only, so cuDNN never rounds operands to TF32.
    EPONA_CUDNN_CHECK(api.cudnnSetConvolutionMathType(p->conv, fp32 ? CUDNN_FMA_MATH : CUDNN_TENSOR_OP_MATH));

    int count = 0;
    EPONA_CUDNN_CHECK(api.cudnnGetConvolutionForwardAlgorithmMaxCount(handle, &count));
    std::vector<cudnnConvolutionFwdAlgoPerf_t> found(static_cast<std::size_t>(std::max(count, 1)));
    int returned = 0;
    EPONA_CUDNN_CHECK(api.cudnnGetConvolutionForwardAlgorithm_v7(handle, p->x, p->w, p->conv, p->y, count, &returned,
                                                                 found.data()));
    for (int i = 0; i < returned; ++i) {
      const auto& r = found[static_cast<std::size_t>(i)];
      if (r.status != CUDNN_STATUS_SUCCESS || !exact_algorithm(r.algo)) continue;
      if (fp32 && r.mathType == CUDNN_TENSOR_OP_MATH) continue;
      std::size_t bytes = 0;
      if (api.cudnnGetConvolutionForwardWorkspaceSize(handle, p->x, p->w, p->conv, p->y, r.algo, &bytes) !=
              CUDNN_STATUS_SUCCESS ||
          bytes > kMaxWorkspace)
        continue;
      p->algo = r.algo;
      p->workspace = bytes;
      if (!fp32) EPONA_CUDNN_CHECK(api.cudnnSetConvolutionMathType(p->conv, r.mathType));
      return p;
    }
    p->unusable = "cuDNN offers no implicit-GEMM algorithm for this geometry";
    return p;
  }

  std::mutex mutex_;
  std::map<int, cudnnHandle_t> handles_;
  std::map<int, std::string> reasons_;
  std::map<std::array<std::int64_t, 9>, std::unique_ptr<Plan>> plans_;
};

inline constexpr bool compiled_in = true;

#else  // no cuDNN headers at build time: the engine reports itself unavailable

class Engine {
 public:
  static Engine& get() {
    static Engine e;
    return e;
  }
  std::string unavailable(Context&) { return "built without cuDNN headers"; }
  void release() {}
  template <class T>
  bool forward(Context&, const T*, const T*, T*, const Conv2dShape&) {
    return false;
  }
  template <class T>
  std::string plan_problem(Context&, const Conv2dShape&) {
    return "built without cuDNN headers";
  }
};

inline constexpr bool compiled_in = false;

#endif

}  // namespace epona::cuda::cudnn
