#!/usr/bin/env bash
# Session 35, call 7: the first machine with two GPUs lent (nvidia-h200-x2). The NCCL cases of the
# sharded DiT test, bench_gpu_shards with its NCCL rows (the VisDiT and the AR step split over both
# GPUs), and the program's --tensor-parallel 2 on --backend cuda against the whole model.
set -u
tar xJf .devcalls/pkg.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkg
OUT=$OUT/s35c7
source tests/cuda/device_env.sh
nccl=$(find / -name 'libnccl.so.2' -not -path '/proc/*' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
nvidia-smi -L | tee $OUT/gpu.txt; nvidia-smi topo -m > $OUT/topo.txt 2>&1
summary "nccl: $nccl"
timeout 240 $BIN/test_cuda_dit_shards > $OUT/test_cuda_dit_shards.log 2>&1
summary "test_cuda_dit_shards rc=$? $(grep -h 'test cases:' $OUT/test_cuda_dit_shards.log) $(grep -h 'assertions:' $OUT/test_cuda_dit_shards.log)"
grep -h "NCCL\|nccl\|skipping" $OUT/test_cuda_dit_shards.log | head -10
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda"
for tp in 1 2; do
  /usr/bin/time -f "%e s" timeout 120 $BIN/epona generate $common -n 3 --tensor-parallel $tp --out $OUT/gen$tp > $OUT/gen$tp.log 2>&1
  summary "epona generate -n 3 --backend cuda --tensor-parallel $tp rc=$? $(tail -1 $OUT/gen$tp.log)"
done
python3 - "$OUT" <<'PY' | tee -a $OUT/summary.txt
import json, sys
o = sys.argv[1]
a = json.load(open(o + "/gen1/trajectory.json")); b = json.load(open(o + "/gen2/trajectory.json"))
def flat(x):
    return [v for e in x for v in (flat(e) if isinstance(e, list) else [e])] if isinstance(x, list) else []
fa = [v for k in sorted(a) for v in flat(a[k]) if isinstance(v, (int, float))]
fb = [v for k in sorted(b) for v in flat(b[k]) if isinstance(v, (int, float))]
d = max((abs(x - y) for x, y in zip(fa, fb)), default=float('nan'))
print(f"trajectory.json: {len(fa)} and {len(fb)} numbers, max abs difference tp2 vs tp1 {d:.3g} m")
PY
timeout 300 $BIN/bench_gpu_shards --repeats 5 > $OUT/bench_shards.txt 2>&1
summary "bench shards rc=$?"; cat $OUT/bench_shards.txt
