#!/usr/bin/env bash
# Session 37, call 1 (nvidia-h200-x2): the peer group (cuda/runtime/peer_shard_sum.cuh), our sum over
# NVLink in place of NCCL's all-reduce. Its tests (one GPU shared, two GPUs), the DiT over it, one
# sum against NCCL's at several block counts, the VisDiT and AR-step rows through both groups side
# by side, and the program's --tensor-parallel 2 through both against the whole model.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c1
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
nvidia-smi topo -m > $OUT/topo.txt 2>&1
for t in test_cuda_peer_shard_sum test_cuda_dit_shards; do
  start=$(date +%s%N)
  timeout 200 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(elapsed $start) $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|skipping" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
timeout 90 $BIN/bench_gpu_shards --only sum --repeats 9 > $OUT/bench_sum.txt 2>&1; summary "bench sum rc=$?"; cat $OUT/bench_sum.txt | tee -a $OUT/summary.txt
timeout 150 $BIN/bench_gpu_shards --only vis --repeats 5 > $OUT/bench_vis.txt 2>&1; summary "bench vis rc=$?"; cat $OUT/bench_vis.txt | tee -a $OUT/summary.txt
timeout 150 $BIN/bench_gpu_shards --only step --repeats 5 > $OUT/bench_step.txt 2>&1; summary "bench step rc=$?"; cat $OUT/bench_step.txt | tee -a $OUT/summary.txt
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
for run in "tp1:--tensor-parallel 1" "peer:--tensor-parallel 2 --shard-sum peer" "nccl:--tensor-parallel 2 --shard-sum nccl" "auto:--tensor-parallel 2"; do
  name=${run%%:*}; flags=${run#*:}
  start=$(date +%s%N)
  timeout 60 $BIN/epona generate $common $flags --out $OUT/gen_$name > $OUT/gen_$name.log 2>&1
  summary "generate $name rc=$? $(elapsed $start) $(tail -1 $OUT/gen_$name.log | cut -c1-200)"
done
