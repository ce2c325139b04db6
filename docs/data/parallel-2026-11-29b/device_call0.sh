#!/usr/bin/env bash
# Session 36, call 0 (nvidia-h200, one GPU): every GPU test program rebuilt after the graph cache
# learnt to fence launches of graphs that hold collectives (graph.hpp, context.hpp,
# nccl_shard_sum.hpp), with the new one-GPU case of the fence, and compute-sanitizer over the
# sharded DiT test's one-GPU NCCL and fence cases. models/ was left behind to stay under 64 MiB.
set -u
tar xJf .devcalls/pkgA.tar.xz -C .devcalls
tar xJf .devcalls/pkg2.tar.xz -C .devcalls
OUT=$OUT/s36c0
BIN=$PWD/.devcalls/pkgA
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
cp .devcalls/pkg/test_cuda_dit_shards .devcalls/pkg/test_cuda_world_parity $BIN/
for t in $BIN/test_cuda_* $BIN/test_apps_engine_cuda; do
  n=$(basename $t)
  timeout 200 $t > $OUT/$n.log 2>&1
  summary "$n rc=$? $(grep -h 'test cases:' $OUT/$n.log | tail -1) $(grep -h 'assertions:' $OUT/$n.log | tail -1)"
done
EPONA_GOLDEN_DIR=$PWD/tests/data/trained timeout 100 $BIN/test_cuda_world_parity > $OUT/world_parity_trained.log 2>&1
summary "world_parity on the trained set rc=$? $(grep -h 'test cases:' $OUT/world_parity_trained.log | tail -1)"
timeout 200 $SAN --tool memcheck --leak-check full $BIN/test_cuda_dit_shards -tc="*fence*,*NCCL group of one*" > $OUT/memcheck_dit_shards.log 2>&1
summary "memcheck dit_shards fence + NCCL-of-one rc=$? $(grep -h 'ERROR SUMMARY\|LEAK SUMMARY' $OUT/memcheck_dit_shards.log | tr '\n' ' ')"
