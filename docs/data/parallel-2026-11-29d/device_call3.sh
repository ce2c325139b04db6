#!/usr/bin/env bash
# Session 38, call 3 (nvidia-h200-x2): after the groups' default became one channel and the
# program took --hide-sums. The peer group's test again; the program through both groups, with
# and without --hide-sums, against the whole model (the bundled model, float32): its note naming
# the group, and how far the latents and plans lie from the whole model's.
set -u
tar xJf .devcalls/pkgH.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgH
OUT=$OUT/s38c3
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
for t in test_cuda_header_units test_cuda_peer_shard_sum; do
  timeout 300 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|logged" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3 --latents"
for run in "whole:" "auto:--tensor-parallel 2" "nccl:--tensor-parallel 2 --shard-sum nccl" "autohide:--tensor-parallel 2 --hide-sums" "ncclhide:--tensor-parallel 2 --shard-sum nccl --hide-sums"; do
  name=${run%%:*}; flags=${run#*:}
  timeout 90 $BIN/epona generate $common $flags --out $OUT/gen_$name > $OUT/gen_$name.log 2>&1
  summary "generate $name rc=$? $(grep -h 'tensor parallel' $OUT/gen_$name.log)"
done
python3 - "$OUT" <<'PY' | tee -a $OUT/summary.txt
import json, sys, numpy as np
out = sys.argv[1]
def load(name):
    return np.load(f"{out}/gen_{name}/latents.npy").astype(np.float64), json.load(open(f"{out}/gen_{name}/trajectory.json"))
w, wt = load("whole")
for name in ["auto", "nccl", "autohide", "ncclhide"]:
    try:
        x, t = load(name)
    except Exception as e:
        print(name, "missing:", e); continue
    rel = np.abs(x - w).max() / np.abs(w).max()
    print(f"{name}: latents within {rel:.3g} of the whole model's (relative to its largest); trajectory.json {'same' if t == wt else 'differs'} from the whole model's")
a, _ = load("auto"); h, _ = load("autohide")
print(f"autohide against auto: latents max abs difference {np.abs(a - h).max():.3g}")
PY
rm -rf $OUT/gen_*/frames
