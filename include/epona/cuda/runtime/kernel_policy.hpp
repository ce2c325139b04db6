// epona/cuda/runtime/kernel_policy.hpp — the CUDA backend's tuning choices in one object: which
// fused or tuned path each kernel family takes. A cuda::Context holds one (ctx.policy(), readable
// and settable) and kernels read the policy of the context they run on, so two contexts of one
// process can differ (side-by-side timing, tests of both paths) without process-wide switches.
// Every field keeps the fast path by default; from_environment() reads the EPONA_CUDA_*
// variables once per process (0/1 flags: anything else is an error naming the variable).
// Graphs recorded before a change keep what they recorded.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <cstring>

#include "epona/core/env.hpp"
#include "epona/core/error.hpp"

namespace epona::cuda {

// Which new cuBLASLt plans time the heuristic's first candidates (gemm/gemm_common.cuh): Off
// none, Large products of at least kTuneRowsMin rows, All every one.
enum class GemmTuning { Off, Large, All };

// Which implementation runs the dense (non-depthwise) convolutions. Auto: bf16 k x k
// convolutions through cuDNN where it is loadable and has an exact algorithm for the geometry
// (implicit GEMM on tensor cores, no im2col traffic); 1x1 ones (plain GEMMs over pixels) and
// every float32 one through cuBLASLt (float32: cuDNN's FMA-only kernels measured 1.4x slower
// than an im2col panel + cuBLASLt's float32 GEMM on an H200). Cudnn: every dense conv through
// cuDNN (an error where it cannot); Gemm: never cuDNN (im2col panel + cuBLASLt for k > 1).
enum class ConvEngine { Auto, Cudnn, Gemm };

struct KernelPolicy {
  // ---- launches and row passes (runtime/device.cuh)
  bool programmatic_launch = true;  // EPONA_CUDA_PDL: programmatic dependent launches (sm_90+)
  bool reversed_passes = true;      // EPONA_CUDA_REVERSE_PASSES: large row passes walk last row first
  bool graphs = true;               // EPONA_CUDA_GRAPHS: GraphCache records and replays (0: runs eagerly)
  bool poison_new_buffers = false;  // (tests) scratch handed out filled with 0xFF bytes (NaN)
  // ---- attention (attention/)
  bool attention_split = true;  // EPONA_CUDA_ATTN_SPLIT: Auto takes the planned TMA kernel
  bool qk_norm_rope_rows = true;  // EPONA_CUDA_QK_ROWS: qk_norm_rope's row kernel (0: head per warp)
  bool attention_qk_norm = true;  // EPONA_CUDA_QK_NORM_ATTN: short attention with the QK LayerNorm inside
  // ---- products (gemm/)
  bool pair_gemm = true;           // EPONA_CUDA_PAIR_GEMM: linear_group as one batched product
  bool skinny_linear = true;       // EPONA_CUDA_SKINNY: the split-K kernel for products of few rows
  bool small_gemm = true;          // EPONA_CUDA_SMALL_GEMM: own kernels for tiny products (0: cuBLASLt)
  bool few_rows_gemm = false;      // EPONA_CUDA_FEW_ROWS_GEMM: bf16 products of 64-2048 rows, own kernel
  bool own_gemm = false;           // EPONA_CUDA_OWN_GEMM: bf16 erf-GELU products, own wgmma kernel
  bool residual_gemm = true;       // EPONA_CUDA_RESIDUAL_GEMM: residual adds inside the product
  GemmTuning gemm_tuning = GemmTuning::Large;  // EPONA_CUDA_GEMM_TUNE: unset Large, 1 All, 0 Off
  // ---- pointwise (pointwise/)
  bool activation_tables = true;  // EPONA_CUDA_TABLES: bf16 lookup tables for large activations
  // ---- convolutions (conv/)
  ConvEngine conv_engine = ConvEngine::Auto;  // EPONA_CUDA_CONV: auto, cudnn or gemm
  bool conv_fusion = true;   // EPONA_CUDA_CONV_FUSE: fused conv epilogues (cuDNN)
  bool conv_tuning = true;   // EPONA_CUDA_CONV_TUNE: time cuDNN vs GEMM for small bf16 k x k convs
  bool dcae_fusion = true;   // EPONA_CUDA_DCAE_FUSE: the DC-AE's fused temporal/shuffle kernels
  static constexpr std::int64_t default_conv_panel_bytes = std::int64_t{512} << 20;
  std::int64_t conv_panel_bytes = default_conv_panel_bytes;  // (tests) the GEMM engine's im2col budget

  // The defaults with every EPONA_CUDA_* variable applied, read on the first call only.
  static const KernelPolicy& from_environment() {
    static const KernelPolicy env = read_environment();
    return env;
  }

 private:
  static KernelPolicy read_environment() {
    struct Flag {
      const char* variable;
      bool KernelPolicy::*field;
    };
    static constexpr Flag flags[] = {
        {"EPONA_CUDA_PDL", &KernelPolicy::programmatic_launch},
        {"EPONA_CUDA_REVERSE_PASSES", &KernelPolicy::reversed_passes},
        {"EPONA_CUDA_GRAPHS", &KernelPolicy::graphs},
        {"EPONA_CUDA_ATTN_SPLIT", &KernelPolicy::attention_split},
        {"EPONA_CUDA_QK_ROWS", &KernelPolicy::qk_norm_rope_rows},
        {"EPONA_CUDA_QK_NORM_ATTN", &KernelPolicy::attention_qk_norm},
        {"EPONA_CUDA_PAIR_GEMM", &KernelPolicy::pair_gemm},
        {"EPONA_CUDA_SKINNY", &KernelPolicy::skinny_linear},
        {"EPONA_CUDA_SMALL_GEMM", &KernelPolicy::small_gemm},
        {"EPONA_CUDA_FEW_ROWS_GEMM", &KernelPolicy::few_rows_gemm},
        {"EPONA_CUDA_OWN_GEMM", &KernelPolicy::own_gemm},
        {"EPONA_CUDA_RESIDUAL_GEMM", &KernelPolicy::residual_gemm},
        {"EPONA_CUDA_TABLES", &KernelPolicy::activation_tables},
        {"EPONA_CUDA_CONV_FUSE", &KernelPolicy::conv_fusion},
        {"EPONA_CUDA_CONV_TUNE", &KernelPolicy::conv_tuning},
        {"EPONA_CUDA_DCAE_FUSE", &KernelPolicy::dcae_fusion},
    };
    KernelPolicy p;
    for (const Flag& f : flags) p.*f.field = env_flag(f.variable, p.*f.field);
    if (const char* v = std::getenv("EPONA_CUDA_GEMM_TUNE"); v && *v)
      p.gemm_tuning = env_flag("EPONA_CUDA_GEMM_TUNE", false) ? GemmTuning::All : GemmTuning::Off;
    p.conv_engine = conv_engine_from_environment();
    return p;
  }
  static ConvEngine conv_engine_from_environment() {
    const char* e = std::getenv("EPONA_CUDA_CONV");
    if (!e || !*e || std::strcmp(e, "auto") == 0) return ConvEngine::Auto;
    if (std::strcmp(e, "cudnn") == 0) return ConvEngine::Cudnn;
    if (std::strcmp(e, "gemm") == 0) return ConvEngine::Gemm;
    fail("EPONA_CUDA_CONV must be auto, cudnn or gemm, got '", e, "'");
  }
};

}  // namespace epona::cuda
