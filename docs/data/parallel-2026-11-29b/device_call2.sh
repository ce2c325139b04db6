#!/usr/bin/env bash
# Session 36, call 2 (nvidia-h200, one GPU): issue #38's AR step + decode with the `fast` preset
# (midpoint 10 / 10) and with midpoint 9 / 9, which the sweep on the bundled model of run 4 found
# within the quality criterion (docs/solvers.md). Each bench_gpu_world run alternates the
# official sampler and one other over two rounds; rollouts of 10 frames with the DC-AE decode
# after each step (serial) and beside the next step, host wall time per frame.
set -u
tar xJf .devcalls/pkgW.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgW
OUT=$OUT/s36c2
source tests/cuda/device_env.sh
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/summary.txt"
for s in midpoint:10:10 midpoint:9:9; do
  n=rollout_${s//:/_}
  timeout 250 $BIN/bench_gpu_world --only step --repeats 6 --rollout-compare 10 --sampler-compare $s > $OUT/$n.out 2> $OUT/$n.err
  summary "$n rc=$?"
  grep -E "\"name\": \"(step|rollout)" $OUT/$n.out | cut -c1-120 | tee -a $OUT/summary.txt
done
timeout 60 $BIN/bench_gpu_dcae --quick --no-f32 > $OUT/dcae.out 2>&1; summary "dcae rc=$?"
grep -E "decode" $OUT/dcae.out | head -4 | cut -c1-160 | tee -a $OUT/summary.txt
