#!/usr/bin/env bash
# Session 37, call 7 (nvidia-h200-x2): the final build, after the GPU groups' shared part moved into
# cuda/runtime/device_shard_threads.hpp. Every header in two units, the groups' and the DiT's tests,
# the program through both groups against the whole model, and the VisDiT rows once more.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c7
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
for t in test_cuda_header_units test_cuda_peer_shard_sum test_cuda_dit_shards; do
  start=$(date +%s%N)
  timeout 300 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(elapsed $start) $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|logged" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
for run in "tp1:--tensor-parallel 1" "auto:--tensor-parallel 2" "nccl:--tensor-parallel 2 --shard-sum nccl"; do
  name=${run%%:*}; flags=${run#*:}
  timeout 60 $BIN/epona generate $common $flags --out $OUT/gen_$name > $OUT/gen_$name.log 2>&1
  summary "generate $name rc=$?"
done
for name in auto nccl; do
  same=0; all=0
  for f in $OUT/gen_tp1/frames/*.png; do all=$((all + 1)); cmp -s $f $OUT/gen_$name/frames/$(basename $f) && same=$((same + 1)); done
  summary "$name: $same of $all frames byte-identical to tp1; trajectory.json $(cmp -s $OUT/gen_$name/trajectory.json $OUT/gen_nccl/trajectory.json && echo same as nccl || echo differs from nccl)"
done
rm -rf $OUT/gen_*
timeout 120 $BIN/bench_gpu_shards --only vis --repeats 5 > $OUT/bench_vis.txt 2>&1; summary "bench vis rc=$?"; grep whole\\\|alone\\\|peer2\\\|nccl2 $OUT/bench_vis.txt | tee -a $OUT/summary.txt
