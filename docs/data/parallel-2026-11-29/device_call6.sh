#!/usr/bin/env bash
# Session 35, call 6: bench_gpu_shards --only block after the review (one block setup timing both
# the block and its attention).
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s35c6
source tests/cuda/device_env.sh
timeout 200 $BIN/bench_gpu_shards --only block --repeats 7 > $OUT/bench_block.txt 2>&1
summary "bench block rc=$?"; cat $OUT/bench_block.txt
