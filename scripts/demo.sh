#!/usr/bin/env bash
# The main job: installs dependencies, builds the `epona` program, then runs `epona generate`
# and `epona plan` on the bundled model (a small Epona trained on the synthetic driving world,
# models/small-synthetic) and its held-out demo clip, writing PNG/JSON/CSV (and, when the build
# has FFmpeg's libraries, an MP4 of the clip) into ./out/demo.
#
#   scripts/demo.sh                                   # the bundled model and clip
#   scripts/demo.sh --weights world.pkl --dcae dcae_td_20000.pkl \
#                   --frames clip/ --poses clip/poses.csv    # the released model
#
# Options of its own: --out DIR (default out/demo), -n/--num-frames N (frames to generate,
# default 6), --cuda / --no-cuda (build the CUDA engine too, or not; default: only when
# `nvidia-smi -L` finds a GPU). Every other option goes to both commands (--steps, --seed,
# --dtype, --threads, --fit, --config, --quiet; see `epona plan --help`). Paths are relative
# to where it is run. EPONA_BUILD_DIR picks the build folder (default: build, inside the
# repository).
set -euo pipefail
caller=$(pwd)
root=$(cd "$(dirname "$0")/.." && pwd)

out=out/demo
frames=6
cuda=auto
pass=()
while (($#)); do
  case "$1" in
    --out|-o) out=${2:?"--out needs a folder"}; shift 2 ;;
    --out=*) out=${1#--out=}; shift ;;
    -n|--num-frames) frames=${2:?"$1 needs a number"}; shift 2 ;;
    --num-frames=*) frames=${1#--num-frames=}; shift ;;
    --cuda) cuda=ON; shift ;;
    --no-cuda) cuda=OFF; shift ;;
    # The help is the comment block under the #! line, up to the first line of code.
    -h|--help) awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"; exit 0 ;;
    *) pass+=("$1"); shift ;;
  esac
done

# nvcc without a GPU would compile the CUDA engine for nothing (it doubles the first build).
if [[ $cuda == auto ]]; then
  cuda=OFF
  if command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1; then cuda=ON; fi
fi

cd "$root"
scripts/setup.sh
build=${EPONA_BUILD_DIR:-build}
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DEPONA_TESTS=OFF -DEPONA_BENCHMARKS=OFF \
      -DEPONA_EXAMPLES=ON -DEPONA_CUDA="$cuda" >/dev/null
cmake --build "$build" -j "$(nproc)" --target epona_cli
epona=$(cd "$build" && pwd)/apps/epona
# The clip as a video too when the build has FFmpeg's libraries (scripts/setup.sh installs them).
video=()
if grep -q '^EPONA_FFMPEG:BOOL=ON' "$build/CMakeCache.txt"; then video=(--video "$out/generate/demo.mp4"); fi

cd "$caller"
echo
echo "== epona generate: roll out $frames frame(s) under the model's own plan"
"$epona" generate "${pass[@]}" --num-frames "$frames" --out "$out/generate" ${video[@]+"${video[@]}"}
echo
echo "== epona plan: the trajectory from the last frames"
"$epona" plan "${pass[@]}" --out "$out/plan"
echo
echo "demo outputs are in $(cd "$out" && pwd):"
echo "  generate/frames/frame_*.png   generated frames"
echo "  generate/contact_sheet.png    input frames (blue) and generated frames (orange), numbered"
((${#video[@]})) && echo "  generate/demo.mp4             the input frames then the generated ones, H.264 at 5 fps"
echo "  generate/trajectory.csv/.json each step's planned trajectory; generate/poses.csv the motion into each frame"
echo "  plan/plan.png                 the planned trajectory drawn top-down over the last frame"
echo "  plan/trajectory.csv/.json     the planned waypoints (x m forward, y m left, yaw deg)"
