#!/usr/bin/env bash
# Session 38, call 4 (nvidia-h200-x2): after the hidden sums were removed again. The peer group's
# test twice (call 3 hung once with two channels of spinning sums on eight streams of one GPU),
# the DiT split over shards and GPUs, and the program's note naming the group it took.
set -u
tar xJf .devcalls/pkgH.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgH
OUT=$OUT/s38c4
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
for t in test_cuda_header_units test_cuda_peer_shard_sum test_cuda_peer_shard_sum test_cuda_dit_shards; do
  timeout 200 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|logged" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
for run in "auto:--tensor-parallel 2" "nccl:--tensor-parallel 2 --shard-sum nccl"; do
  name=${run%%:*}; flags=${run#*:}
  timeout 90 $BIN/epona generate $common $flags --out $OUT/gen_$name > $OUT/gen_$name.log 2>&1
  summary "generate $name rc=$? $(grep -h 'tensor parallel' $OUT/gen_$name.log)"
done
summary "trajectory.json auto against nccl: $(cmp -s $OUT/gen_auto/trajectory.json $OUT/gen_nccl/trajectory.json && echo same || echo differs)"
rm -rf $OUT/gen_*/
