#!/usr/bin/env bash
# Session 37, call 4 (nvidia-h200-x2): the peer group with its chosen default (128 blocks, call 3).
# Its tests and the DiT's again, compute-sanitizer's memcheck over the peer group's test, and the
# program's default (--shard-sum auto) against the whole model in float32 and bf16, with the whole
# model's own bf16-against-float32 distance beside it for scale.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c4
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
for run in "tp1:--tensor-parallel 1" "auto:--tensor-parallel 2" "tp1_bf16:--dtype bf16" "auto_bf16:--tensor-parallel 2 --dtype bf16"; do
  name=${run%%:*}; flags=${run#*:}
  start=$(date +%s%N)
  timeout 60 $BIN/epona generate $common $flags --out $OUT/gen_$name > $OUT/gen_$name.log 2>&1
  summary "generate $name rc=$? $(elapsed $start)"
done
sed -n '/^python3 - "$OUT" <<.PY./,/^PY$/p' docs/data/parallel-2026-11-29c/device_call3.sh \
  | sed 's/\[("peer", "tp1"), ("nccl", "tp1"), ("peer_bf16", "tp1_bf16")\]/[("auto", "tp1"), ("auto_bf16", "tp1_bf16"), ("tp1_bf16", "tp1")]/' > $OUT/compare.sh
OUT=$OUT bash $OUT/compare.sh
rm -rf $OUT/gen_* $OUT/compare.sh
