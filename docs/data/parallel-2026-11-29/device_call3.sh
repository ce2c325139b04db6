#!/usr/bin/env bash
# Session 35, call 1: every GPU test program after the header kernels became templates, the engine
# test linking the program's own CUDA engine, and the two-unit header test; the trained parity; the
# `epona` program itself on the GPU (built without FFmpeg); then bench_gpu_shards --only block
# (tensor against sequence parallelism on one block).
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s35c1
source tests/cuda/device_env.sh
nvidia-smi -L | tee $OUT/gpu.txt
for p in test_apps_engine_cuda epona; do summary "$p unresolved libraries: $(ldd $BIN/$p | grep 'not found' | tr '\n' ' ')"; done
for t in $BIN/test_cuda_* $BIN/test_apps_engine_cuda; do
  n=$(basename $t)
  timeout 300 $t > $OUT/$n.log 2>&1
  summary "$n rc=$? $(grep -h 'test cases:' $OUT/$n.log | tail -1)"
done
grep -h "sm_90a code" $OUT/test_cuda_header_units.log | head -2
EPONA_GOLDEN_DIR=$PWD/tests/data/trained timeout 200 $BIN/test_cuda_world_parity > $OUT/world_parity_trained.log 2>&1
summary "world_parity trained rc=$? $(grep -h 'test cases:' $OUT/world_parity_trained.log)"
M=$PWD/models/small-synthetic
timeout 120 $BIN/epona plan --backend cuda --weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors \
  --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --out $OUT/plan > $OUT/plan.log 2>&1
summary "epona plan --backend cuda rc=$? $(tail -2 $OUT/plan.log | tr '\n' ' ')"
timeout 60 $BIN/epona plan --backend cuda --tensor-parallel 2 --weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors \
  --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --out $OUT/plan2 > $OUT/plan2.log 2>&1
summary "epona plan --tensor-parallel 2 on one GPU rc=$? $(tail -1 $OUT/plan2.log)"
timeout 200 $BIN/bench_gpu_shards --only block --repeats 7 > $OUT/bench_block.txt 2>&1
summary "bench block rc=$?"; cat $OUT/bench_block.txt
