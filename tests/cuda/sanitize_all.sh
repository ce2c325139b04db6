#!/usr/bin/env bash
# compute-sanitizer over the whole GPU test suite on a GPU machine: memcheck (with leak check)
# on every GPU test program, racecheck on the programs whose kernels share memory between
# threads. Programs run several at a time (the sanitizers are slow; the GPU has room), each
# with a time limit. Logs go to <out>; one summary line per run to stdout and <out>/summary.txt.
# Exits 1 if any run reports an error, a hazard or fails its tests.
# Usage: tests/cuda/sanitize_all.sh <dir with test_cuda_* / test_apps_engine_cuda> <out dir> [jobs]
set -u
BIN=$(cd "$1" && pwd)
OUT=$2
JOBS=${3:-4}
source "$(dirname "$0")/device_env.sh"
LIMIT=${SANITIZE_TIMEOUT:-540}

# tool, program: one sanitizer run; prints its summary line.
sanitize() {
  local tool=$1 prog=$2 log="$OUT/$1_$(basename "$2").log" args=()
  case $tool in
    memcheck) args=(--tool memcheck --leak-check full)
              # test_cuda_memory provokes CUDA API errors on purpose (out-of-memory, bad sizes)
              [[ $prog == *test_cuda_memory ]] && args+=(--report-api-errors no) ;;
    racecheck) args=(--tool racecheck --racecheck-report all) ;;
  esac
  local start=$SECONDS
  timeout "$LIMIT" "$SAN" "${args[@]}" --error-exitcode 99 "$prog" >"$log" 2>&1
  local rc=$?
  local verdict=ok
  ((rc == 0)) || verdict=FAIL
  echo "$verdict $tool $(basename "$prog") rc=$rc $((SECONDS - start)) s: $(grep -E '(ERROR|RACECHECK) SUMMARY' "$log" | tail -1 | sed 's/^========= //') | $(grep -E 'test cases:' "$log" | tail -1 | tr -s ' ')"
}

runs=()
for p in "$BIN"/test_cuda_* "$BIN"/test_apps_engine_cuda; do
  [[ -x $p ]] || continue
  runs+=("memcheck $p")
  case $(basename "$p") in  # kernels with shared memory / warp-level exchange
    test_cuda_attention|test_cuda_pointwise|test_cuda_fused_passes|test_cuda_dcae_ops|test_cuda_dcae_layers|test_cuda_dcae_temporal|test_cuda_gemm)
      runs+=("racecheck $p") ;;
  esac
done

nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/summary.txt"
for r in "${runs[@]}"; do
  while (($(jobs -rp | wc -l) >= JOBS)); do wait -n; done
  sanitize $r >>"$OUT/summary.txt" &
done
wait
grep -E '^(ok|FAIL) ' "$OUT/summary.txt" | sort
! grep -q '^FAIL ' "$OUT/summary.txt"
