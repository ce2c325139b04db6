#!/usr/bin/env bash
# Session 35, call 8: call 7's NCCL runs hung on two GPUs. The same with CUDA_MODULE_LOADING=EAGER
# (a kernel module loaded lazily synchronises its context, which can wait on an NCCL kernel that
# waits on the other GPU's thread).
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s35c8
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0 CUDA_MODULE_LOADING=EAGER
timeout 150 $BIN/test_cuda_dit_shards -tc="*NCCL*" > $OUT/test_cuda_dit_shards.log 2>&1
summary "EAGER test_cuda_dit_shards NCCL cases rc=$? $(grep -h 'test cases:' $OUT/test_cuda_dit_shards.log) $(grep -h 'assertions:' $OUT/test_cuda_dit_shards.log)"
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
timeout 60 $BIN/epona generate $common --out $OUT/gen1 > $OUT/gen1.log 2>&1; summary "EAGER generate tp1 rc=$?"
timeout 90 $BIN/epona generate $common --tensor-parallel 2 --out $OUT/gen2 > $OUT/gen2.log 2>&1; summary "EAGER generate tp2 rc=$? $(tail -1 $OUT/gen2.log)"
cmp $OUT/gen1/trajectory.json $OUT/gen2/trajectory.json && summary "trajectory.json identical" || { summary "trajectory.json differs:"; head -c 600 $OUT/gen1/trajectory.json; echo; head -c 600 $OUT/gen2/trajectory.json; }
timeout 150 $BIN/bench_gpu_shards --only vis --repeats 3 > $OUT/bench_vis.txt 2>&1
summary "EAGER bench vis rc=$?"; cat $OUT/bench_vis.txt
