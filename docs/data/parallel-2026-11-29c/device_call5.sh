#!/usr/bin/env bash
# Session 37, call 5 (nvidia-h200-x2): after each pair's peer mapping is enabled once per process
# (call 4's memcheck listed CUDA's "already enabled" reports). The group's tests, memcheck over
# them, the DiT's tests, and the program's --tensor-parallel 2 once more.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c5
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
for t in test_cuda_peer_shard_sum test_cuda_dit_shards; do
  start=$(date +%s%N)
  timeout 300 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(elapsed $start) $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|skipping\|logged" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
start=$(date +%s%N)
timeout 240 $SAN --tool memcheck --leak-check full $BIN/test_cuda_peer_shard_sum > $OUT/memcheck.log 2>&1
summary "memcheck test_cuda_peer_shard_sum rc=$? $(elapsed $start) $(grep -h 'ERROR SUMMARY\|LEAK SUMMARY\|test cases:' $OUT/memcheck.log | tr '\n' ' ')"
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
timeout 60 $BIN/epona generate $common --tensor-parallel 2 --out $OUT/gen > $OUT/gen.log 2>&1
summary "generate --tensor-parallel 2 rc=$?"
timeout 60 $BIN/epona generate $common --tensor-parallel 2 --shard-sum bogus --out $OUT/bad > $OUT/bad.log 2>&1
summary "generate --shard-sum bogus rc=$? $(tail -1 $OUT/bad.log)"
rm -rf $OUT/gen $OUT/bad
