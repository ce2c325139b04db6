#!/usr/bin/env bash
# Session 36, call 1 (nvidia-h200-x2): the two-GPU hang of session 35. First the bare repro
# (raw CUDA + NCCL, nccl_deadlock_repro.cu) without and with the fences, then the group with its
# fences: the NCCL cases of test_cuda_dit_shards, --tensor-parallel 2 against 1 through the
# program, and bench_gpu_shards' VisDiT and AR-step rows over both GPUs.
set -u
tar xJf .devcalls/pkg2.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s36c1
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
nvidia-smi -L > $OUT/gpu.txt
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
for mode in unfenced fenced; do
  start=$(date +%s%N)
  timeout 40 $BIN/nccl_deadlock_repro $mode > $OUT/repro_$mode.log 2>&1
  summary "repro $mode rc=$? $(elapsed $start) last: $(tail -1 $OUT/repro_$mode.log)"
done
# run_or_dump SECONDS LOG CMD...: runs CMD; if it is still running after SECONDS, dumps every
# thread's stack (gdb, where the machine has it) into LOG.stacks and kills it.
run_or_dump() {
  local limit=$1 log=$2; shift 2
  "$@" > "$log" 2>&1 & local pid=$!
  for ((i = 0; i < limit; ++i)); do kill -0 $pid 2>/dev/null || { wait $pid; return $?; }; sleep 1; done
  command -v gdb > /dev/null && timeout 60 gdb -p $pid -batch -ex "thread apply all bt" > "$log.stacks" 2>&1
  kill -9 $pid; wait $pid; return 124
}
NCCL_DEBUG=INFO NCCL_DEBUG_FILE=$OUT/nccl.%p.log run_or_dump 330 $OUT/test_cuda_dit_shards.log $BIN/test_cuda_dit_shards
summary "test_cuda_dit_shards rc=$? $(grep -h 'test cases:' $OUT/test_cuda_dit_shards.log) $(grep -h 'assertions:' $OUT/test_cuda_dit_shards.log)"
grep -h "NCCL\|through NCCL\|no progress" $OUT/test_cuda_dit_shards.log | head -12
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
for tp in 1 2; do
  start=$(date +%s%N)
  run_or_dump 60 $OUT/gen$tp.log $BIN/epona generate $common --tensor-parallel $tp --out $OUT/gen$tp
  summary "generate tp$tp rc=$? $(elapsed $start) $(tail -1 $OUT/gen$tp.log)"
done
cmp $OUT/gen1/trajectory.json $OUT/gen2/trajectory.json && summary "trajectory.json: tp2 identical to tp1" || summary "trajectory.json: tp2 differs from tp1"
for f in $OUT/gen1/*.png; do cmp -s $f $OUT/gen2/$(basename $f) || summary "differs: $(basename $f)"; done
EPONA_GOLDEN_DIR=$PWD/tests/data/trained timeout 60 $BIN/test_cuda_world_parity > $OUT/world_parity_trained.log 2>&1
summary "world_parity on the trained set rc=$? $(grep -h 'test cases:' $OUT/world_parity_trained.log | tail -1)"
timeout 120 $BIN/bench_gpu_shards --only vis --repeats 5 > $OUT/bench_vis.txt 2>&1; summary "bench vis rc=$?"
cat $OUT/bench_vis.txt
