#!/usr/bin/env bash
# Session 35, call 3: compute-sanitizer memcheck (leak check) over the engine test, which now runs
# the program's own CUDA engine, and the two-unit header test.
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s35c3
source tests/cuda/device_env.sh
for t in test_cuda_header_units test_apps_engine_cuda; do
  timeout 400 $SAN --tool memcheck --leak-check full $BIN/$t > $OUT/$t.memcheck.log 2>&1
  summary "memcheck $t rc=$? $(grep -h 'test cases:' $OUT/$t.memcheck.log | tail -1) $(grep -h 'ERROR SUMMARY\|LEAK SUMMARY' $OUT/$t.memcheck.log | tr '\n' ' ')"
done
