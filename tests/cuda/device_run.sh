#!/usr/bin/env bash
# Runs the prebuilt GPU tests, compute-sanitizer (memcheck on every GPU test, racecheck on
# attention) and the kernel micro-benchmark on a GPU machine, in one go. Binaries are built
# elsewhere (no doctest/Eigen needed here). Logs go to <out>; a compact summary to stdout.
# Usage: tests/cuda/device_run.sh <dir with test_cuda_* and bench_cuda_kernels> <out dir> [profile]
# With `profile`, Nsight Compute then profiles one launch of each own kernel (clocks as found).
set -u
BIN=$(cd "$1" && pwd)
OUT=$2
source "$(dirname "$0")/device_env.sh"

nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu,power.draw --format=csv \
  | tee -a "$OUT/summary.txt"
summary "cublasLt: ${lt:-not found}"

for t in memory gemm pointwise attention; do
  start=$(date +%s%N)
  timeout 180 "$BIN/test_cuda_$t" >>"$OUT/tests.log" 2>&1
  rc=$?
  ms=$(( ($(date +%s%N) - start) / 1000000 ))
  summary "test_cuda_$t rc=$rc (${ms} ms): $(grep -E 'test cases:' "$OUT/tests.log" | tail -1)"
done
grep -E "^  (linear|attention|layer_norm|rms|apply|gelu|silu|add)" "$OUT/tests.log" \
  | awk '{ if ($0 ~ /rel_l2/) n++ } END { print "  measured checks:", n }' | tee -a "$OUT/summary.txt"
grep -A12 -E "ERROR|FAILED|CHECK\(" "$OUT/tests.log" | head -60

timeout 150 "$BIN/bench_cuda_kernels" >"$OUT/bench.log" 2>&1
summary "bench rc=$?"
cat "$OUT/bench.log"

for t in gemm pointwise attention memory; do
  extra=""
  [ "$t" = memory ] && extra="--report-api-errors no"  # that test provokes API errors on purpose
  timeout 120 "$SAN" --tool memcheck --leak-check full $extra "$BIN/test_cuda_$t" >>"$OUT/sanitizer.log" 2>&1
  summary "memcheck test_cuda_$t rc=$? $(grep -E 'ERROR SUMMARY' "$OUT/sanitizer.log" | tail -1)"
done
timeout 150 "$SAN" --tool racecheck --racecheck-report all "$BIN/test_cuda_attention" >>"$OUT/sanitizer.log" 2>&1
summary "racecheck test_cuda_attention rc=$? $(grep -E 'RACECHECK SUMMARY|ERROR SUMMARY' "$OUT/sanitizer.log" | tail -1)"

[ "${3:-}" = profile ] || exit 0
NCU=$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -1)
timeout 240 "$NCU" --clock-control none -k "regex:flash_|layer_norm_packed|rms_norm_heads|rope_kernel|for_each_pack" \
  --section SpeedOfLight --section Occupancy --section LaunchStats --section WarpStateStats \
  --section ComputeWorkloadAnalysis --section MemoryWorkloadAnalysis \
  "$BIN/bench_cuda_kernels" --once >"$OUT/ncu.txt" 2>&1
summary "ncu rc=$? ($NCU)"
grep -E "^  [a-zA-Z_].*\(|Duration|Compute \(SM\) Throughput|^    Memory Throughput|Achieved Occupancy|Registers Per Thread|Issue Slots Busy|Warp Cycles Per Issued" \
  "$OUT/ncu.txt" | sed -E 's/ +/ /g' | cut -c1-110
OBJ=$(command -v cuobjdump || echo /usr/local/cuda/bin/cuobjdump)
"$OBJ" -sass "$BIN/test_cuda_attention" >"$OUT/sass.txt" 2>&1
awk '/Function : .*flash_bf16_kernelILb1/{f=1} /Function : /{if($0 !~ /flash_bf16_kernelILb1/) f=0} f' "$OUT/sass.txt" \
  | grep -oE "HMMA[.A-Z0-9]*|LDSM[.A-Z0-9]*|MUFU.EX2|LDGSTS[.A-Z0-9]*|LDL|STL" | sort | uniq -c | tee -a "$OUT/summary.txt"
