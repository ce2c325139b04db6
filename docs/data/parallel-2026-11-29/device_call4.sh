#!/usr/bin/env bash
# Session 35, call 2: the GPU test programs call 1 could not carry (the 64 MiB limit), after the
# header kernels became templates.
set -u
tar xJf .devcalls/pkgB.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s35c2
source tests/cuda/device_env.sh
for t in $BIN/test_cuda_*; do
  n=$(basename $t)
  timeout 200 $t > $OUT/$n.log 2>&1
  summary "$n rc=$? $(grep -h 'test cases:' $OUT/$n.log | tail -1)"
done
