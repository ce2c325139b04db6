#!/usr/bin/env bash
# Session 36, call 4 (nvidia-h200-x2): call 1 found the real fault behind the two-GPU hang: the
# kernels' dynamic shared memory attribute was set once per process, so GPU 1's launches of those
# kernels were refused (cudaErrorInvalidValue). With it set per device: the NCCL cases of
# test_cuda_dit_shards, --tensor-parallel 2 against 1 through the program, and bench_gpu_shards'
# VisDiT and AR-step rows over both GPUs.
set -u
tar xJf .devcalls/pkg4.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg4
OUT=$OUT/s36c4
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
timeout 240 $BIN/test_cuda_dit_shards > $OUT/test_cuda_dit_shards.log 2>&1
summary "test_cuda_dit_shards rc=$? $(grep -h 'test cases:' $OUT/test_cuda_dit_shards.log) $(grep -h 'assertions:' $OUT/test_cuda_dit_shards.log)"
grep -h "through NCCL\|no progress\|ERROR" $OUT/test_cuda_dit_shards.log | head -12 | tee -a $OUT/summary.txt
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
for tp in 1 2; do
  start=$(date +%s%N)
  timeout 60 $BIN/epona generate $common --tensor-parallel $tp --out $OUT/gen$tp > $OUT/gen$tp.log 2>&1
  summary "generate tp$tp rc=$? $(elapsed $start) $(tail -1 $OUT/gen$tp.log | cut -c1-200)"
done
python3 - "$OUT" <<'PY' | tee -a $OUT/summary.txt
import json, sys
o = sys.argv[1]
a = json.load(open(o + "/gen1/trajectory.json")); b = json.load(open(o + "/gen2/trajectory.json"))
def nums(x):
    if isinstance(x, dict): return [v for k in sorted(x) for v in nums(x[k])]
    if isinstance(x, list): return [v for e in x for v in nums(e)]
    return [x] if isinstance(x, (int, float)) and not isinstance(x, bool) else []
fa, fb = nums(a), nums(b)
d = max((abs(x - y) for x, y in zip(fa, fb)), default=float("nan"))
print(f"trajectory.json: {len(fa)} and {len(fb)} numbers, max abs difference tp2 vs tp1 {d:.3g}")
PY
for f in $OUT/gen1/frames/*.png; do cmp -s $f $OUT/gen2/frames/$(basename $f) && s=same || s=differs; summary "frame $(basename $f): $s"; done
timeout 120 $BIN/bench_gpu_shards --only vis --repeats 5 > $OUT/bench_vis.txt 2>&1; summary "bench vis rc=$?"; cat $OUT/bench_vis.txt | tee -a $OUT/summary.txt
timeout 150 $BIN/bench_gpu_shards --only step --repeats 5 > $OUT/bench_step.txt 2>&1; summary "bench step rc=$?"; cat $OUT/bench_step.txt | tee -a $OUT/summary.txt
