#!/usr/bin/env bash
# Session 38, call 5 (nvidia-h200-x2): the rollout (step + decode beside it) with the peer kernel
# in 64 and in 128 blocks, one run of the bench each, to see whether fewer spinning blocks leave the
# decode on GPU 0 more room than the slower sums cost.
set -u
tar xJf .devcalls/pkgH.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgH
OUT=$OUT/s38c5
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
for blocks in 64 128; do
  timeout 250 $BIN/bench_gpu_shards --only rollout --repeats 3 --peer-blocks $blocks > $OUT/bench_rollout_blocks$blocks.txt 2>&1
  summary "bench rollout, $blocks blocks rc=$?"; grep name $OUT/bench_rollout_blocks$blocks.txt | tee -a $OUT/summary.txt
done
