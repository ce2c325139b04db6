#!/usr/bin/env bash
# Session 34, call 1: tensor parallelism of the DiTs (issue #40) on one H200: the sharded DiT test
# (shards sharing the GPU; the NCCL case skips with one GPU), the GPU programs whose blocks changed
# (attention width and the shard sums in dit_blocks.hpp), memcheck over the sharded test, then
# bench_gpu_shards (whole VisDiT vs one shard of 2 and of 4, sums left out).
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s34c1
source tests/cuda/device_env.sh
nccl=$(find / -name 'libnccl.so.2' -not -path '/proc/*' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
nvidia-smi -L | tee $OUT/gpu.txt
summary "nccl: $nccl"
for t in test_cuda_dit_shards test_cuda_blocks_world test_cuda_dit_stream_pair test_cuda_world_parity; do
  timeout 240 $BIN/$t > $OUT/$t.log 2>&1; summary "$t rc=$? $(grep -h 'test cases' $OUT/$t.log) $(grep -h 'assertions' $OUT/$t.log)"
done
grep -h "MESSAGE\|rel L2\|skipping" -A0 $OUT/test_cuda_dit_shards.log | head -40
EPONA_GOLDEN_DIR=$PWD/tests/data/trained timeout 120 $BIN/test_cuda_world_parity > $OUT/world_parity_trained.log 2>&1
summary "world_parity trained rc=$? $(grep -h 'assertions' $OUT/world_parity_trained.log)"
timeout 150 $BIN/bench_gpu_shards --repeats 5 > $OUT/bench_shards.txt 2>&1
summary "bench shards rc=$?"; cat $OUT/bench_shards.txt
timeout 200 $SAN --tool memcheck --leak-check full $BIN/test_cuda_dit_shards > $OUT/shards_memcheck.log 2>&1
summary "memcheck shards rc=$? $(grep -h 'ERROR SUMMARY\|LEAK SUMMARY' $OUT/shards_memcheck.log | tr '\n' ' ')"
