#!/usr/bin/env bash
# Session 34, call 2: the GPU tests after the review moves (the world model's split case now in
# world_parity.cu, the NCCL group's one-GPU case), the CUDA engine test after the engine split
# (model_engine.hpp), and the program: plan on the GPU, and --tensor-parallel refused on one GPU.
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s34c2
source tests/cuda/device_env.sh
nccl=$(find / -name 'libnccl.so.2' -not -path '/proc/*' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
for t in test_cuda_dit_shards test_cuda_world_parity test_apps_engine_cuda; do
  timeout 240 $BIN/$t > $OUT/$t.log 2>&1; summary "$t rc=$? $(grep -h 'test cases' $OUT/$t.log) $(grep -h 'assertions' $OUT/$t.log)"
done
grep -h "MESSAGE" -A0 $OUT/test_cuda_world_parity.log | grep -i "shard" | head -4
grep -h "NCCL\|skipping" $OUT/test_cuda_dit_shards.log | head -6
EPONA_GOLDEN_DIR=$PWD/tests/data/trained timeout 120 $BIN/test_cuda_world_parity > $OUT/world_parity_trained.log 2>&1
summary "world_parity trained rc=$? $(grep -h 'assertions' $OUT/world_parity_trained.log)"
grep -h "shard" $OUT/world_parity_trained.log | head -2
export EPONA_DATA_DIR=$PWD/tests/data
timeout 60 $BIN/epona plan --backend cuda --out $OUT/plan --seed 7 > $OUT/plan.log 2>&1; summary "plan cuda rc=$?"
timeout 60 $BIN/epona plan --backend cuda --out $OUT/plan2 --seed 7 --tensor-parallel 2 > $OUT/plan2.log 2>&1; summary "plan cuda --tensor-parallel 2 rc=$? $(tail -1 $OUT/plan2.log)"
timeout 60 $BIN/epona plan --backend cpu --out $OUT/plan3 --seed 7 --tensor-parallel 2 > $OUT/plan3.log 2>&1; summary "plan cpu --tensor-parallel 2 rc=$? $(head -1 $OUT/plan3.log)"
