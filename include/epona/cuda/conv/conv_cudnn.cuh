// epona/cuda/conv/conv_cudnn.cuh — the cuDNN engine of the GPU convolutions: channels-last (NHWC)
// forward convolutions through cuDNN 9's convolution API, loaded at run time (dlopen), so
// nothing links against cuDNN and a machine without it falls back to the GEMM engine. float32
// uses FMA math only (never TF32); bf16 uses tensor cores with float32 accumulation. Fuses
// bias, ReLU and a residual input into the convolution's epilogue where cuDNN accepts it.
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

#include "epona/core/env.hpp"
#include "epona/core/dtype.hpp"
#include "epona/core/shapes.hpp"
#include "epona/cuda/runtime/context.hpp"
#include "epona/cuda/runtime/scratch.hpp"

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
// The fused conv + bias (+ residual) + activation entry points: optional (without them every
// convolution runs unfused).
#define EPONA_CUDNN_FUSED_FUNCTIONS(X)                                                                  \
  X(cudnnConvolutionBiasActivationForward) X(cudnnCreateActivationDescriptor)                           \
  X(cudnnSetActivationDescriptor) X(cudnnDestroyActivationDescriptor)

// Timed algorithm choice (EPONA_CUDNN_FIND=1): optional.
#define EPONA_CUDNN_FIND_FUNCTIONS(X) X(cudnnFindConvolutionForwardAlgorithm)

struct Api {
#define EPONA_CUDNN_POINTER(name) decltype(&::name) name = nullptr;
  EPONA_CUDNN_FUNCTIONS(EPONA_CUDNN_POINTER)
  EPONA_CUDNN_FUSED_FUNCTIONS(EPONA_CUDNN_POINTER)
  EPONA_CUDNN_FIND_FUNCTIONS(EPONA_CUDNN_POINTER)
#undef EPONA_CUDNN_POINTER
  std::size_t version = 0;
  std::string unavailable;  // why cuDNN cannot be used here (empty when it can)

  bool ok() const { return unavailable.empty(); }
  bool has_fused() const {
    return cudnnConvolutionBiasActivationForward && cudnnCreateActivationDescriptor && cudnnSetActivationDescriptor &&
           cudnnDestroyActivationDescriptor;
  }

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
#define EPONA_CUDNN_RESOLVE_OPTIONAL(name) a.name = reinterpret_cast<decltype(&::name)>(dlsym(lib, #name));
    EPONA_CUDNN_FUSED_FUNCTIONS(EPONA_CUDNN_RESOLVE_OPTIONAL)
    EPONA_CUDNN_FIND_FUNCTIONS(EPONA_CUDNN_RESOLVE_OPTIONAL)
#undef EPONA_CUDNN_RESOLVE_OPTIONAL
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

  // The fused form (cudnnConvolutionBiasActivationForward): bias descriptors in the map type and
  // in float32 (which one cuDNN accepts is found on the first call), ReLU / identity activations
  // (identity needs the precomputed-index implicit GEMM). State per activation: 0 untried,
  // 1 bias in the map type, 2 bias in float32, -1 refused (fused_unusable says why).
  cudnnTensorDescriptor_t bias_same = nullptr, bias_f32 = nullptr;
  cudnnActivationDescriptor_t relu = nullptr, identity = nullptr;
  std::size_t identity_workspace = 0;
  int fused_state[2] = {0, 0};  // [0] identity, [1] ReLU
  std::string fused_unusable[2];

  Plan() = default;
  Plan(const Plan&) = delete;
  Plan& operator=(const Plan&) = delete;
  ~Plan() {  // destructors must not throw: statuses at teardown are not reported
    const Api& api = Api::get();
    if (relu) api.cudnnDestroyActivationDescriptor(relu);
    if (identity) api.cudnnDestroyActivationDescriptor(identity);
    if (bias_same) api.cudnnDestroyTensorDescriptor(bias_same);
    if (bias_f32) api.cudnnDestroyTensorDescriptor(bias_f32);
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

// EPONA_CUDNN_FIND=1: plans take the fastest exact algorithm by cuDNN's own timing
// (cudnnFindConvolutionForwardAlgorithm, once per geometry, outside any graph recording) instead
// of its heuristic's first choice.
inline bool timed_choice() {
  static const bool on = env_flag("EPONA_CUDNN_FIND", false);
  return on;
}

template <class T>
__global__ void widen_kernel(const T* in, float* out, std::int64_t n) {
  const std::int64_t i = blockIdx.x * std::int64_t{blockDim.x} + threadIdx.x;
  if (i < n) out[i] = static_cast<float>(in[i]);
}

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

  // y = act(conv(x) + bias + z) in one cuDNN call (act: ReLU or none; z may be null, or alias y
  // for an in-place residual add: each output element reads its own z before it is written).
  // False when cuDNN, the geometry or the fused form is unavailable for it: the caller then
  // runs conv + separate passes. cuDNN's answer is found on the first call per geometry and
  // activation (bias in the map type, else float32) and remembered; later failures throw.
  template <class T>
  bool forward_fused(Context& ctx, const T* x, const T* w, const T* bias, const T* z, T* y, const Conv2dShape& s,
                     bool relu) {
    std::lock_guard<std::mutex> lock(mutex_);
    const Api& api = Api::get();
    const cudnnHandle_t handle = handle_or_reason(ctx).first;
    if (!handle || !api.has_fused() || !bias) return false;
    Plan& plan = plan_for<T>(ctx, handle, s);
    if (!plan.unusable.empty()) return false;
    const int a = relu ? 1 : 0;
    if (plan.fused_state[a] < 0) return false;
    if (plan.fused_state[a] == 0 && !prepare_fused<T>(handle, plan, s, a)) return false;
    EPONA_CUDNN_CHECK(api.cudnnSetStream(handle, ctx.stream()));
    // identity needs the precomputed-index implicit GEMM; ReLU runs the plan's algorithm
    const cudnnConvolutionFwdAlgo_t algo = relu ? plan.algo : CUDNN_CONVOLUTION_FWD_ALGO_IMPLICIT_PRECOMP_GEMM;
    const std::size_t ws_bytes = relu ? plan.workspace : plan.identity_workspace;
    Tensor<unsigned char, Cuda> workspace;
    if (ws_bytes) workspace = scratch_tensor<unsigned char>(ctx, {static_cast<std::int64_t>(ws_bytes)});
    Tensor<float, Cuda> bias_f32;
    const auto call = [&](int form) {
      const void* b = bias;
      if (form == 2 && !std::is_same_v<T, float>) {
        bias_f32 = scratch_tensor<float>(ctx, {s.out_channels});
        widen(ctx, bias, bias_f32.data(), s.out_channels);
        b = bias_f32.data();
      }
      const float alpha1 = 1.0f, alpha2 = z ? 1.0f : 0.0f;
      return api.cudnnConvolutionBiasActivationForward(
          handle, &alpha1, plan.x, x, plan.w, w, plan.conv, algo, workspace.data(), ws_bytes, &alpha2, plan.y,
          z ? static_cast<const void*>(z) : static_cast<const void*>(y), form == 2 ? plan.bias_f32 : plan.bias_same, b,
          relu ? plan.relu : plan.identity, plan.y, y);
    };
    if (plan.fused_state[a] > 0) {
      EPONA_CUDNN_CHECK(call(plan.fused_state[a]));
      return true;
    }
    std::string why;
    for (const int form : {1, 2}) {
      if (form == 2 && std::is_same_v<T, float>) break;
      const cudnnStatus_t status = call(form);
      if (status == CUDNN_STATUS_SUCCESS) {
        plan.fused_state[a] = form;
        return true;
      }
      why += std::string(why.empty() ? "" : "; ") + (form == 1 ? "bias in the map type: " : "float32 bias: ") +
             api.cudnnGetErrorString(status);
    }
    plan.fused_state[a] = -1;
    plan.fused_unusable[a] = "cudnnConvolutionBiasActivationForward refused (" + why + ")";
    return false;
  }

  // How the fused form fared per geometry so far: "" where every tried geometry fused, else
  // the reasons (tests and benchmarks print it).
  std::string fused_report() {
    std::lock_guard<std::mutex> lock(mutex_);
    std::string r;
    for (const auto& [key, plan] : plans_)
      for (int a = 0; a < 2; ++a)
        if (plan && plan->fused_state[a] < 0)
          r += std::string(r.empty() ? "" : " | ") + std::to_string(key[3]) + "->" + std::to_string(key[6]) + " k" +
               std::to_string(key[7]) + (a ? " relu: " : " identity: ") + plan->fused_unusable[a];
    return r;
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
  Plan& plan_for(Context& ctx, cudnnHandle_t handle, const Conv2dShape& s) {
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
    // the heuristic's ranking, or (EPONA_CUDNN_FIND=1) cuDNN's timing of every algorithm, fastest first
    if (timed_choice() && api.cudnnFindConvolutionForwardAlgorithm)
      EPONA_CUDNN_CHECK(api.cudnnFindConvolutionForwardAlgorithm(handle, p->x, p->w, p->conv, p->y, count, &returned,
                                                                 found.data()));
    else
      EPONA_CUDNN_CHECK(api.cudnnGetConvolutionForwardAlgorithm_v7(handle, p->x, p->w, p->conv, p->y, count,
                                                                   &returned, found.data()));
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

  // Descriptors of the fused form for activation a (0 identity, 1 ReLU); false (remembered)
  // when one cannot be made.
  template <class T>
  static bool prepare_fused(cudnnHandle_t handle, Plan& p, const Conv2dShape& s, int a) {
    const Api& api = Api::get();
    const auto refuse = [&](const std::string& why) {
      p.fused_state[a] = -1;
      p.fused_unusable[a] = why;
      return false;
    };
    const int O = static_cast<int>(s.out_channels);
    const cudnnDataType_t type = std::is_same_v<T, float> ? CUDNN_DATA_FLOAT : CUDNN_DATA_BFLOAT16;
    if (!p.bias_same) {
      if (api.cudnnCreateTensorDescriptor(&p.bias_same) != CUDNN_STATUS_SUCCESS ||
          api.cudnnSetTensor4dDescriptor(p.bias_same, CUDNN_TENSOR_NHWC, type, 1, O, 1, 1) != CUDNN_STATUS_SUCCESS ||
          api.cudnnCreateTensorDescriptor(&p.bias_f32) != CUDNN_STATUS_SUCCESS ||
          api.cudnnSetTensor4dDescriptor(p.bias_f32, CUDNN_TENSOR_NHWC, CUDNN_DATA_FLOAT, 1, O, 1, 1) !=
              CUDNN_STATUS_SUCCESS)
        return refuse("bias descriptor");
    }
    cudnnActivationDescriptor_t& act = a ? p.relu : p.identity;
    if (!act) {
      if (api.cudnnCreateActivationDescriptor(&act) != CUDNN_STATUS_SUCCESS ||
          api.cudnnSetActivationDescriptor(act, a ? CUDNN_ACTIVATION_RELU : CUDNN_ACTIVATION_IDENTITY,
                                           CUDNN_PROPAGATE_NAN, 0.0) != CUDNN_STATUS_SUCCESS)
        return refuse("activation descriptor");
    }
    if (a == 0) {
      std::size_t bytes = 0;
      if (api.cudnnGetConvolutionForwardWorkspaceSize(handle, p.x, p.w, p.conv, p.y,
                                                      CUDNN_CONVOLUTION_FWD_ALGO_IMPLICIT_PRECOMP_GEMM,
                                                      &bytes) != CUDNN_STATUS_SUCCESS ||
          bytes > kMaxWorkspace)
        return refuse("no precomputed-index implicit GEMM for the identity epilogue");
      p.identity_workspace = bytes;
    }
    return true;
  }

  // bias (T) -> float32 for the fused form's float32 bias.
  template <class T>
  static void widen(Context& ctx, const T* in, float* out, std::int64_t n) {
    widen_kernel<<<static_cast<unsigned>((n + 255) / 256), 256, 0, ctx.stream()>>>(in, out, n);
    EPONA_CUDA_CHECK(cudaGetLastError());
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
  bool forward_fused(Context&, const T*, const T*, const T*, const T*, T*, const Conv2dShape&, bool) {
    return false;
  }
  std::string fused_report() { return ""; }
  template <class T>
  std::string plan_problem(Context&, const Conv2dShape&) {
    return "built without cuDNN headers";
  }
};

inline constexpr bool compiled_in = false;

#endif

}  // namespace epona::cuda::cudnn
