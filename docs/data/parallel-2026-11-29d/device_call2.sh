#!/usr/bin/env bash
# Session 38, call 2 (nvidia-h200-x2): issue #40's AR step + decode measured (rollout rows: the
# decode beside the next step on GPU 0), and the hidden sums with fewer sum blocks (the kernel's
# blocks then leave the other multiprocessors to the products).
set -u
tar xJf .devcalls/pkgH.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgH
OUT=$OUT/s38c2
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
timeout 240 $BIN/bench_gpu_shards --only rollout --repeats 3 > $OUT/bench_rollout.txt 2>&1
summary "bench rollout rc=$?"; grep name $OUT/bench_rollout.txt | tee -a $OUT/summary.txt
for blocks in 16 32; do
  timeout 150 $BIN/bench_gpu_shards --only vis --repeats 5 --peer-blocks $blocks > $OUT/bench_vis_blocks$blocks.txt 2>&1
  summary "bench vis, $blocks blocks rc=$?"; grep name $OUT/bench_vis_blocks$blocks.txt | grep peer | tee -a $OUT/summary.txt
done
