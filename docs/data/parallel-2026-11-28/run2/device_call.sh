#!/usr/bin/env bash
# Session 29, device call 1 (nvidia-h200-x2): issue #40's data parallelism on the GPUs — mpirun -np 2
# epona eval / generate --clips with --backend cuda against one process (same report, time), and
# NCCL's collectives at the VisDiT's sizes (what model parallelism would pay).
set -u
mkdir -p .device-build && tar xJf .devcalls/pkg.tar.xz -C .device-build
BIN=$PWD/.device-build/pkg OUT=$OUT/logs
source tests/cuda/device_env.sh
export NCCL_NVLS_ENABLE=0 OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
nccl=$(find / -name 'libnccl.so.2' -not -path '/proc/*' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
nvidia-smi --query-gpu=index,name,driver_version --format=csv,noheader | tee "$OUT/summary.txt"
{ which mpirun; mpirun --version | head -1; echo "nccl: $nccl"; nproc; } 2>&1 | tee -a "$OUT/summary.txt"
export EPONA_MODEL_DIR=$PWD/models/small-synthetic
E=$BIN/epona
ldd $E | grep -E "not found|mpi" | tee -a "$OUT/summary.txt"
W=$PWD/.dev29 && mkdir -p $W
$E synth --clips 16 --frames 10 --future 2 --out $W/clips -q --threads 16
watch_gpus() { while :; do nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader >> "$1"; sleep 0.5; done; }
timed() { local n=$1; shift; local s=$(date +%s%N); "$@" > "$OUT/$n.out" 2> "$OUT/$n.err"; local rc=$?; local e=$(date +%s%N); summary "$n rc=$rc $(( (e - s) / 1000000 )) ms"; }
ARGS="--clips $W/clips --steps 100 --horizon 2 --backend cuda --threads 4 -q"
for dtype in float32 bfloat16; do
  for round in 1 2; do
    timed eval1_${dtype}_$round $E eval $ARGS --dtype $dtype --json $OUT/e1_${dtype}_$round.json
    watch_gpus "$OUT/gpus_${dtype}_$round.csv" & wp=$!
    timed eval2_${dtype}_$round mpirun -np 2 --bind-to none $E eval $ARGS --dtype $dtype --json $OUT/e2_${dtype}_$round.json
    kill $wp
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
    rel = max((abs(x - y) / max(abs(x), abs(y), 1e-12) for _, x, y in d if isinstance(x, float) and isinstance(y, float)), default=0)
    print(names[i], "vs", names[j], ":", "equal" if not d else "%d values differ, max rel %.3g, first %s" % (len(d), rel, d[0]))
PY
  awk -F', ' '{split($3,m," "); if (m[1]+0 > 1000) used[$1]=1} END {for (g in used) printf "GPU %s used; ", g; print ""}' "$OUT/gpus_${dtype}_1.csv" | tee -a "$OUT/summary.txt"
done
GARGS="--clips $W/clips -n 4 --steps 100 --backend cuda --dtype bfloat16 --threads 4 -q"
for round in 1 2; do
  rm -rf $W/g1 $W/g2
  timed gen1_$round $E generate $GARGS --out $W/g1
  timed gen2_$round mpirun -np 2 --bind-to none $E generate $GARGS --out $W/g2
done
same=0; diff=0
for c in $W/g1/clip_*; do n=$(basename $c); if cmp -s $c/trajectory.json $W/g2/$n/trajectory.json && cmp -s $c/frames/frame_0003.png $W/g2/$n/frames/frame_0003.png; then same=$((same+1)); else diff=$((diff+1)); fi; done
summary "generate --clips: $same clips identical, $diff differ (1 vs 2 processes)"
cd "$OUT" && tar cJf ../logs.tar.xz .
