#!/usr/bin/env bash
# The world model's GPU checks in one go on a GPU machine: the two test programs (golden
# parity in float32 and bf16, blocks vs the CPU), compute-sanitizer memcheck over both, and
# optionally the real-configuration benchmark or the side-by-side run with the official code.
# Binaries are built elsewhere (tests/cuda/device_run.sh says how). Logs go to <out>.
# Usage: tests/cuda/world_device_run.sh <bin dir> <out dir> [tests|memcheck|bench|side <official checkout>]...
set -u
BIN=$(cd "$1" && pwd)
OUT=$2
shift 2
source "$(dirname "$0")/device_env.sh"
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu --format=csv,noheader | tee -a "$OUT/summary.txt"

while [ $# -gt 0 ]; do
  case "$1" in
    tests)
      for t in world_parity blocks_world; do
        start=$(date +%s)
        timeout 300 "$BIN/test_cuda_$t" -s >"$OUT/test_$t.log" 2>&1
        rc=$?
        summary "test_cuda_$t rc=$rc ($(( $(date +%s) - start )) s): $(grep -E 'test cases:' "$OUT/test_$t.log" | tail -1)"
        grep -E "assertions:|ERROR|FAILED" "$OUT/test_$t.log" | head -20
        grep -E "MESSAGE: .*rel" "$OUT/test_$t.log" | sed -E 's/.*MESSAGE: //' | sort -u | head -80
      done ;;
    memcheck)
      for t in world_parity blocks_world; do
        start=$(date +%s)
        timeout "${MEMCHECK_TIMEOUT:-420}" "$SAN" --tool memcheck --leak-check full "$BIN/test_cuda_$t" >"$OUT/memcheck_$t.log" 2>&1
        summary "memcheck test_cuda_$t rc=$? ($(( $(date +%s) - start )) s): $(grep -E 'ERROR SUMMARY' "$OUT/memcheck_$t.log" | tail -1) $(grep -E 'test cases:' "$OUT/memcheck_$t.log" | tail -1)"
      done ;;
    bench)
      timeout 400 "$BIN/bench_gpu_world" --repeats 10 >"$OUT/bench_world.jsonl" 2>"$OUT/bench_world.err"
      summary "bench_gpu_world rc=$?"
      cat "$OUT/bench_world.jsonl" | cut -c1-200; tail -5 "$OUT/bench_world.err" ;;
    side)
      bash benchmarks/gpu_side_by_side.sh "$2" "$BIN" "$OUT/side" 2>&1 | tee "$OUT/side_by_side.txt"
      shift ;;
    *) echo "unknown step $1"; exit 2 ;;
  esac
  shift
done
