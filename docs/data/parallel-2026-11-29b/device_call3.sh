#!/usr/bin/env bash
# Session 36, call 3 (nvidia-h200, one GPU, 6.5 s): the engine test after make_engine moved into
# cli.cpp (its unit now links the definition), and compute-sanitizer memcheck over it.
set -u
tar xJf .devcalls/pkgE.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgE OUT=$OUT/s36c3
source tests/cuda/device_env.sh
timeout 200 $BIN/test_apps_engine_cuda > $OUT/engine.log 2>&1
summary "test_apps_engine_cuda rc=$? $(grep -h 'test cases:' $OUT/engine.log) $(grep -h 'assertions:' $OUT/engine.log)"
timeout 300 $SAN --tool memcheck --leak-check full $BIN/test_apps_engine_cuda > $OUT/memcheck.log 2>&1
summary "memcheck rc=$? $(grep -h 'ERROR SUMMARY\|LEAK SUMMARY' $OUT/memcheck.log | tr '\n' ' ')"
