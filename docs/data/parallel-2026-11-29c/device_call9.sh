#!/usr/bin/env bash
# Session 37, call 9 (nvidia-h200-x4, lent at the end of the session): #40's 4-GPU rows.
# bench_gpu_shards' VisDiT and AR-step rows split over 2 and 4 GPUs through the peer group and NCCL.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c9
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
nvidia-smi topo -m > $OUT/topo.txt 2>&1
timeout 130 $BIN/bench_gpu_shards --only vis --repeats 5 > $OUT/bench_vis.txt 2>&1; summary "bench vis rc=$?"; cat $OUT/bench_vis.txt | tee -a $OUT/summary.txt
timeout 150 $BIN/bench_gpu_shards --only step --repeats 5 > $OUT/bench_step.txt 2>&1; summary "bench step rc=$?"; cat $OUT/bench_step.txt | tee -a $OUT/summary.txt
