#!/usr/bin/env bash
# Session 29, device call 3 (nvidia-h200-x2): the program now picks GPU kernels without timing
# (ComputeOptions::reproducible). Reports of 1 vs 2 processes, float32 and bf16, twice each; and
# one process on 1, 8 and 16 clips to separate the fixed start-up from the per-clip time.
set -u
mkdir -p .device-build && tar xJf .devcalls/pkg.tar.xz -C .device-build
BIN=$PWD/.device-build/pkg OUT=$OUT/logs
source tests/cuda/device_env.sh
export NCCL_NVLS_ENABLE=0 OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
export EPONA_MODEL_DIR=$PWD/models/small-synthetic
nvidia-smi --query-gpu=index,name --format=csv,noheader | tee "$OUT/summary.txt"
E=$BIN/epona
W=$PWD/.dev29 && mkdir -p $W
$E synth --clips 16 --frames 10 --future 2 --out $W/clips -q --threads 16
timed() { local n=$1; shift; local s=$(date +%s%N); "$@" > "$OUT/$n.out" 2> "$OUT/$n.err"; local rc=$?; local e=$(date +%s%N); summary "$n rc=$rc $(( (e - s) / 1000000 )) ms"; }
ARGS="--clips $W/clips --steps 100 --horizon 2 --backend cuda --threads 4 -q"
for dtype in float32 bfloat16; do
  for round in 1 2; do
    timed eval1_${dtype}_$round $E eval $ARGS --dtype $dtype --json $OUT/e1_${dtype}_$round.json
    timed eval2_${dtype}_$round mpirun -np 2 --bind-to none $E eval $ARGS --dtype $dtype --json $OUT/e2_${dtype}_$round.json
  done
  python3 - $OUT/e1_${dtype}_1.json $OUT/e1_${dtype}_2.json $OUT/e2_${dtype}_1.json $OUT/e2_${dtype}_2.json <<'PY' | tee -a "$OUT/summary.txt"
import json, sys, itertools
names = ["one#1", "one#2", "two#1", "two#2"]
reps = [json.load(open(p)) for p in sys.argv[1:5]]
for r in reps: r["settings"].pop("processes")
def diffs(a, b, path=""):
    if isinstance(a, dict):
        for k in a: yield from diffs(a[k], b.get(k), path + "." + k)
    elif isinstance(a, list):
        for i, (x, y) in enumerate(zip(a, b)): yield from diffs(x, y, path + "[%d]" % i)
    elif a != b:
        yield path, a, b
for (i, a), (j, b) in itertools.combinations(enumerate(reps), 2):
    d = list(diffs(a, b))
    print(names[i], "vs", names[j], ":", "equal" if not d else "%d values differ, first %s" % (len(d), d[0]))
PY
done
for round in 1 2; do
  for n in 1 8 16; do timed limit${n}_bf16_$round $E eval $ARGS --dtype bfloat16 --limit $n --json $OUT/l$n.json; done
done
cd "$OUT" && tar cJf ../logs.tar.xz summary.txt *.json
