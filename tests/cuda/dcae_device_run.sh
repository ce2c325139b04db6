#!/usr/bin/env bash
# Runs the prebuilt DC-AE GPU tests, bench_gpu_dcae (new beside an older build, same call) and
# compute-sanitizer memcheck on a GPU machine in one go (binaries built elsewhere: the GPU
# machine has no doctest/Eigen). cuDNN is loaded at run time: the first libcudnn.so.9 found on
# the machine goes on the path. Summaries go to stdout and <out dir>/summary.txt.
# Usage: tests/cuda/dcae_device_run.sh <dir with test_cuda_dcae_* and bench_gpu_dcae> <out dir>
#        [tests|bench|all] [dir with an older bench_gpu_dcae to time beside it]
set -u
BIN=$(cd "$1" && pwd)
OUT=$2
WHAT=${3:-all}
OLD=${4:-}
source "$(dirname "$0")/device_env.sh"
ms() { echo $(( ($(date +%s%N) - $1) / 1000000 )); }
TESTS="dcae_temporal dcae_ops dcae_layers dcae_model"

nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu,power.draw --format=csv,noheader \
  | tee -a "$OUT/summary.txt"
summary "cublasLt: ${lt:-not found}; cudnn: ${dnn:-not found}"

if [ "$WHAT" != bench ]; then
  for t in $TESTS; do
    [ -x "$BIN/test_cuda_$t" ] || continue
    start=$(date +%s%N)
    timeout 120 "$BIN/test_cuda_$t" >"$OUT/$t.log" 2>&1
    rc=$?
    summary "test_cuda_$t rc=$rc ($(ms $start) ms): $(grep -E 'test cases:' "$OUT/$t.log" | tail -1)"
    grep -B3 -A12 -E "ERROR|FAILED" "$OUT/$t.log" | head -40
  done
  # the checks of the fused kernels, worst first per kind, and the bf16 golden figures
  grep -hE "temporal fused|upsample pair|relu_linear_attention .*8192" "$OUT"/dcae_temporal.log \
    "$OUT"/dcae_ops.log | sed 's/  */ /g' | tee -a "$OUT/summary.txt" | head -40
  grep -hE "official bf16" "$OUT"/dcae_model.log | sed 's/  */ /g' | tee -a "$OUT/summary.txt" | head -12
fi

# Steps past the first bench and the sanitizer are skipped once the call has run BUDGET seconds.
BUDGET=${BUDGET:-200}
bench() {  # name, then [VAR=value ...] command args...
  local name=$1 start=$(date +%s%N)
  shift
  env "$@" >"$OUT/bench_$name.log" 2>&1
  summary "bench $name rc=$? ($(ms $start) ms)"
  grep -hE '"dcae_(de|en)code"' "$OUT/bench_$name.log" | sed 's/, "peak_mib.*//; s/"gflop.*"tflops"/"tflops"/'
}
pieces() {
  for f in "$@"; do
    [ -f "$OUT/bench_$f.log" ] || continue
    echo "--- pieces ($f)"
    grep -hE '"(decode_part|layer)_' "$OUT/bench_$f.log" | sed 's/{"name": "//; s/", "dtype".*"ms": / /; s/, "tflops".*//' | paste -sd' '
  done
}

if [ "$WHAT" != tests ]; then
  bench new timeout 100 "$BIN/bench_gpu_dcae" --quick --stages --layers
  [ -n "$OLD" ] && bench old timeout 100 "$OLD/bench_gpu_dcae" --quick --stages
  pieces new old
fi

if [ "$WHAT" != bench ]; then
  mc() {  # test name, doctest args...
    local t=$1 start=$(date +%s%N)
    shift
    echo "=== memcheck test_cuda_$t $*" >>"$OUT/memcheck.log"
    timeout 90 "$SAN" --tool memcheck --leak-check full "$BIN/test_cuda_$t" "$@" >"$OUT/mc.tmp" 2>&1
    local rc=$?
    cat "$OUT/mc.tmp" >>"$OUT/memcheck.log"
    summary "memcheck test_cuda_$t $* rc=$rc ($(ms $start) ms) $(grep -E 'ERROR SUMMARY' "$OUT/mc.tmp" | tail -1) $(grep -E 'LEAK SUMMARY' "$OUT/mc.tmp" | tail -1)"
  }
  mc dcae_temporal
  mc dcae_ops
  [ $SECONDS -lt $BUDGET ] && mc dcae_model '-tc=*bf16: every*,cuDNN state released*'
  [ $SECONDS -lt $BUDGET ] && mc dcae_layers
  rm -f "$OUT/mc.tmp"
  grep -B2 -A8 "Invalid\|Leaked" "$OUT/memcheck.log" | grep -E "Invalid|Leaked|Host Frame" | head -24
fi

if [ "$WHAT" != tests ]; then
  # the DC-AE fusions and the measured engine choice off (same build), the choice alone off,
  # cuDNN's timed algorithm choice, and the two builds again
  [ $SECONDS -lt $BUDGET ] && bench unfused EPONA_CUDA_DCAE_FUSE=0 EPONA_CUDA_CONV_TUNE=0 timeout 60 \
    "$BIN/bench_gpu_dcae" --quick --no-f32 --layers
  [ $SECONDS -lt $BUDGET ] && bench notune EPONA_CUDA_CONV_TUNE=0 timeout 60 "$BIN/bench_gpu_dcae" --quick --no-f32
  [ $SECONDS -lt $BUDGET ] && bench find EPONA_CUDNN_FIND=1 timeout 60 "$BIN/bench_gpu_dcae" --quick --no-f32
  [ $SECONDS -lt $BUDGET ] && [ -n "$OLD" ] && bench old2 timeout 60 "$OLD/bench_gpu_dcae" --quick
  [ $SECONDS -lt $BUDGET ] && bench new2 timeout 60 "$BIN/bench_gpu_dcae" --quick --no-f32
  pieces unfused
fi
grep -h "measured faster" "$OUT"/bench_new.log 2>/dev/null | tee -a "$OUT/summary.txt"
summary "total ${SECONDS} s"
# at most 8 files come back from the device tool: the logs travel as one archive
(cd "$OUT" && tar czf logs.tgz *.log && rm -f *.log)
