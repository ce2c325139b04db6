#!/usr/bin/env bash
# Session 38, call 1 (nvidia-h200-x2): the blocks hide their sums (the groups' two channels). The
# GPU tests of the groups and the split DiTs, then the VisDiT and the AR step over two GPUs with
# the sums in the open and hidden, through both groups, side by side in one run.
set -u
tar xJf .devcalls/pkgH.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgH
OUT=$OUT/s38c1
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
nvidia-smi --query-gpu=name --format=csv,noheader | tee -a $OUT/summary.txt
for t in test_cuda_header_units test_cuda_peer_shard_sum test_cuda_dit_shards; do
  timeout 300 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|logged" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
for only in vis step; do
  timeout 200 $BIN/bench_gpu_shards --only $only --repeats 5 > $OUT/bench_$only.txt 2>&1
  summary "bench $only rc=$?"; grep row $OUT/bench_$only.txt | tee -a $OUT/summary.txt
done
