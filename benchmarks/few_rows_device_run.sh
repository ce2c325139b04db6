#!/usr/bin/env bash
# The few-rows GEMM experiment (include/epona/cuda/gemm/gemm_few_rows.cuh) in one device call:
#   1. bench_cuda_small_kernels --only few_rows: each condition-stream shape in cuBLASLt, the
#      few-rows GEMM (its pick, with and without programmatic launches) and each tile;
#   2. its tests in test_cuda_gemm, plainly and under compute-sanitizer memcheck;
#   3. the world model's parity, block and stream-pair tests with EPONA_CUDA_FEW_ROWS_GEMM=1;
#   4. bench_gpu_world's DiT rows with the switch off and on, alternating, two rounds.
# Prints a compact summary (also <out>/summary.txt); logs in <out>.
# Package (here): scripts/device_package.sh build <pkg> test_cuda_gemm test_cuda_world_parity \
#   test_cuda_blocks_world test_cuda_dit_stream_pair bench_cuda_small_kernels bench_gpu_world
# Usage (repository root, on the GPU machine): benchmarks/few_rows_device_run.sh <pkg> <out dir> [step]...
# (steps: rows tests world; all three when none is named)
set -u
BIN=$(cd "$1" && pwd)
OUT=$2
shift 2
STEPS=" ${*:-rows tests world} "
step() { [[ $STEPS == *" $1 "* ]]; }
source "$(dirname "$0")/../tests/cuda/device_env.sh"
cases() { grep -E 'test cases:' "$1" | tail -1 | tr -s ' '; }
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu --format=csv,noheader | tee -a "$OUT/summary.txt"

if step rows; then
  timeout 240 "$BIN/bench_cuda_small_kernels" --only few_rows --repeats 20 >"$OUT/few_rows.txt" 2>&1
  summary "bench few_rows rc=$?"
  grep '^#' "$OUT/few_rows.txt" | grep -v profiled | tee -a "$OUT/summary.txt"
fi

if step tests; then
  timeout 180 "$BIN/test_cuda_gemm" -tc='*few-rows*' >"$OUT/test_gemm.log" 2>&1
  summary "test_cuda_gemm few-rows rc=$?: $(cases "$OUT/test_gemm.log")"
  grep -B2 -A8 -E "ERROR|FAILED" "$OUT/test_gemm.log" | head -40
  timeout 300 "$SAN" --tool memcheck --leak-check full --error-exitcode 99 "$BIN/test_cuda_gemm" -tc='*few-rows*' \
    >"$OUT/memcheck_gemm.log" 2>&1
  summary "memcheck test_cuda_gemm few-rows rc=$?: $(grep 'ERROR SUMMARY' "$OUT/memcheck_gemm.log" | tail -1)"

  for t in world_parity blocks_world dit_stream_pair; do
    EPONA_CUDA_FEW_ROWS_GEMM=1 timeout 300 "$BIN/test_cuda_$t" >"$OUT/test_$t.log" 2>&1
    summary "test_cuda_$t (switch on) rc=$?: $(cases "$OUT/test_$t.log")"
    grep -B2 -A8 -E "ERROR|FAILED" "$OUT/test_$t.log" | head -20
  done
fi

if step world; then
  for round in 1 2; do
    for on in 0 1; do
      EPONA_CUDA_FEW_ROWS_GEMM=$on timeout 200 "$BIN/bench_gpu_world" --only traj_eval,traj_sample,vis_eval,vis_sample \
        --repeats 5 >"$OUT/world_${on}_$round.jsonl" 2>"$OUT/world_${on}_$round.err"
      summary "bench_gpu_world switch=$on round $round rc=$?"
      grep -v '^#' "$OUT/world_${on}_$round.jsonl" | cut -c1-160 | tee -a "$OUT/summary.txt"
    done
  done
fi
