#!/usr/bin/env bash
# The flow-solver quality sweep (docs/solvers.md): writes a synthetic held-out clip set, then runs
# `epona eval` for every solver x step count on it (benchmarks/solver_sweep.py) and writes a
# markdown table, a JSON file and a plot into the output folder.
#
#   scripts/solver_sweep.sh                                  # 10 clips, horizon 2, the bundled model
#   scripts/solver_sweep.sh --clips 200 --horizon 5 --out out/sweep-200
#   scripts/solver_sweep.sh -- --weights world.pkl --dcae dcae_td_20000.pkl --backend cuda
#
# Options: --clips N (default 10), --seed S of the clip set (default 7: held out from the bundled
# model's training seed 1000), --horizon N (default 2), --no-video (planner only), --out DIR
# (default out/solver-sweep), --solvers a,b, --steps 5,10,..; anything after -- goes to eval.
# EPONA_BIN picks the program (default build/apps/epona, a Release build).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bin=${EPONA_BIN:-$root/build/apps/epona}
clips=10 seed=7 horizon=2 out=out/solver-sweep
sweep=()
while [[ $# -gt 0 ]]; do
  case $1 in
    --clips) clips=$2; shift 2 ;;
    --seed) seed=$2; shift 2 ;;
    --horizon) horizon=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --no-video) sweep+=(--no-video); shift ;;
    --solvers|--steps|--threads) sweep+=("$1" "$2"); shift 2 ;;
    --) shift; break ;;
    *) echo "solver_sweep.sh: unknown option '$1' (see the header of $0)" >&2; exit 1 ;;
  esac
done
[[ -x $bin ]] || { echo "solver_sweep.sh: no epona program at $bin (build it, or set EPONA_BIN)" >&2; exit 1; }
set_dir=$out/clips-seed$seed-n$clips-h$horizon
if [[ ! -d $set_dir ]]; then
  "$bin" synth --seed "$seed" --clips "$clips" --frames 10 --future "$horizon" --out "$set_dir" -q
fi
extra=()
[[ $# -gt 0 ]] && extra=(-- "$@")
exec "${PYTHON:-/usr/bin/python3}" "$root/benchmarks/solver_sweep.py" --epona "$bin" --clips "$set_dir" --out "$out" \
  --horizon "$horizon" "${sweep[@]}" "${extra[@]}"
