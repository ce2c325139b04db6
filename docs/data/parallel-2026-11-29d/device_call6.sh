#!/usr/bin/env bash
# Session 38, call 6 (nvidia-h200): after the review moved the rollout rows' frame decode into one
# helper (benchmarks/gpu_frame_decode.cuh) for bench_gpu_world and bench_gpu_shards: both benches'
# rollout rows run (10 steps, one repeat: a check that they run, not figures).
set -u
tar xJf .devcalls/pkgH.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgH
OUT=$OUT/s38c6
source tests/cuda/device_env.sh
timeout 150 $BIN/bench_gpu_shards --only rollout --repeats 1 --steps 10 > $OUT/bench_shards_rollout.txt 2>&1
summary "bench_gpu_shards --only rollout rc=$?"; grep name $OUT/bench_shards_rollout.txt | tee -a $OUT/summary.txt
timeout 200 $BIN/bench_gpu_world --only step --repeats 1 --steps 10 --rollout-compare 2 > $OUT/bench_world_rollout.txt 2>&1
summary "bench_gpu_world --rollout-compare 2 rc=$?"; grep rollout_ $OUT/bench_world_rollout.txt | head -4 | tee -a $OUT/summary.txt
