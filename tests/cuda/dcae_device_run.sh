#!/usr/bin/env bash
# Runs the prebuilt DC-AE GPU tests, compute-sanitizer memcheck over them and bench_gpu_dcae on
# a GPU machine in one go (binaries built elsewhere: the GPU machine has no doctest/Eigen).
# cuDNN is loaded at run time: the first libcudnn.so.9 found on the machine goes on the path.
# Usage: tests/cuda/dcae_device_run.sh <dir with test_cuda_dcae_* and bench_gpu_dcae> <out dir> [tests|bench|all]
set -u
BIN=$(cd "$1" && pwd)
OUT=$2
WHAT=${3:-all}
mkdir -p "$OUT"
lt=$(find /usr/local /opt /usr/lib -name 'libcublasLt.so.13' 2>/dev/null | head -1)
dnn=$(find /usr/local /opt /usr/lib -name 'libcudnn.so.9' 2>/dev/null | head -1)
export LD_LIBRARY_PATH="$(dirname "${lt:-/usr/local/cuda/lib64/x}"):$(dirname "${dnn:-/usr/local/cuda/lib64/x}"):/usr/local/cuda/lib64:${LD_LIBRARY_PATH:-}:$BIN/lib"
SAN=$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)
summary() { echo "$*" | tee -a "$OUT/summary.txt"; }

nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu,power.draw --format=csv,noheader \
  | tee -a "$OUT/summary.txt"
summary "cublasLt: ${lt:-not found}; cudnn: ${dnn:-not found}"

if [ "$WHAT" != bench ]; then
  for t in dcae_ops dcae_layers dcae_model; do
    start=$(date +%s%N)
    timeout 150 "$BIN/test_cuda_$t" >"$OUT/$t.log" 2>&1
    rc=$?
    summary "test_cuda_$t rc=$rc ($(( ($(date +%s%N) - start) / 1000000 )) ms): $(grep -E 'test cases:' "$OUT/$t.log" | tail -1)"
    grep -B3 -A10 -E "ERROR|FAILED|CHECK\(|REQUIRE\(" "$OUT/$t.log" | head -40
  done
  grep -hE "cuDNN engine|rel_max =" "$OUT"/dcae_ops.log "$OUT"/dcae_model.log | head -60
fi

if [ "$WHAT" != tests ]; then
  timeout 200 "$BIN/bench_gpu_dcae" ${BENCH_ARGS:-} >"$OUT/bench.log" 2>&1
  summary "bench rc=$?"
  cat "$OUT/bench.log"
  # the unfused path (no BatchNorm folding, no fused conv epilogues) beside it, same call
  EPONA_CUDA_CONV_FUSE=0 timeout 100 "$BIN/bench_gpu_dcae" --quick --stages >"$OUT/bench_unfused.log" 2>&1
  summary "bench unfused rc=$?"
  cat "$OUT/bench_unfused.log"
fi

if [ "$WHAT" != bench ]; then
  for t in dcae_ops dcae_layers dcae_model; do
    echo "=== memcheck test_cuda_$t" >>"$OUT/memcheck.log"
    timeout 100 "$SAN" --tool memcheck --leak-check full "$BIN/test_cuda_$t" >"$OUT/mc.tmp" 2>&1
    rc=$?
    cat "$OUT/mc.tmp" >>"$OUT/memcheck.log"
    summary "memcheck test_cuda_$t rc=$rc $(grep -E 'ERROR SUMMARY' "$OUT/mc.tmp" | tail -1) $(grep -E 'LEAK SUMMARY' "$OUT/mc.tmp" | tail -1)"
  done
  # the same with cuDNN off the library path (GEMM engine): the sanitizer on our own code alone
  echo "=== memcheck test_cuda_dcae_model without cuDNN" >>"$OUT/memcheck.log"
  LD_LIBRARY_PATH=$(echo "$LD_LIBRARY_PATH" | sed "s|$(dirname "${dnn:-/none/x}"):||") \
    timeout 100 "$SAN" --tool memcheck --leak-check full "$BIN/test_cuda_dcae_model" >"$OUT/mc.tmp" 2>&1
  rc=$?
  cat "$OUT/mc.tmp" >>"$OUT/memcheck.log"
  summary "memcheck test_cuda_dcae_model (no cuDNN) rc=$rc $(grep -E 'ERROR SUMMARY' "$OUT/mc.tmp" | tail -1) $(grep -m1 -o 'cuDNN engine: .*' "$OUT/mc.tmp")"
  rm -f "$OUT/mc.tmp"
  grep -B2 -A8 "Invalid\|Leaked" "$OUT/memcheck.log" | grep -E "Invalid|Leaked|Host Frame" | head -24
fi
