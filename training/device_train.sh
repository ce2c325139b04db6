#!/usr/bin/env bash
# The training of docs/training.md on a lent GPU machine, in device calls of at most 10 minutes.
# Run from the repository root there, with the official checkout carried in .official/ and a
# CPU-portable `epona` (EPONA_NATIVE=OFF) with its libgomp in .device-build/pkg/ (see
# docs/training.md "Reproducing"). State lives in $EPONA_TRAIN_WORK (default /tmp/epona-train),
# which survives between calls while the machine stays warm.
#
#   training/device_train.sh start  OUT   # data, DC-AE, latents, the first world-model chunk
#   training/device_train.sh resume OUT   # more world-model training (WORLD_SECONDS), preview
#   training/device_train.sh retrain OUT  # run 2: from the bundled model (INIT), natural clips plus
#                                         # clips of the exploring driver, the first world chunk
#                                         # (then `resume` with the same knobs)
#
# A device call returns at most 8 files from its output folder: fetch the exported weights in a
# call of their own before anything else writes there (run 3's weights were lost that way).
#
# Both copy the exported model (bf16 safetensors + configs.json), the loss curves and the
# preview into OUT. Knobs (environment): CLIPS, FRAMES, DATA_SEED, DCAE_SECONDS, WORLD_SECONDS,
# WORLD_SCHEDULE (the world model's planned total seconds over all chunks), BATCH, and for retrain
# INIT (default models/small-synthetic), EXPLORE_SEED, EXPLORE_CLIPS, EXPLORE_SHARE, LR.
set -euo pipefail
phase=${1:?start or resume} out=${2:?output folder}
work=${EPONA_TRAIN_WORK:-/tmp/epona-train}
official=.official
epona=.device-build/pkg/epona
export PYTHONUNBUFFERED=1 LD_LIBRARY_PATH=$PWD/.device-build/pkg/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
train() { python3 training/train.py "$@" --official "$official" --work "$work" --data "$work/data"; }

# Clips of the synthetic world as npy, for training: seed, clips, frames, folder[, --explore].
synth_data() {
  "$epona" synth --seed "$1" --clips "$2" --frames "$3" --future 0 --format npy --out "$4" --quiet "${@:5}"
}
gpu_name() { nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true; }

collect() {
  mkdir -p "$out"
  cp "$work"/small/* "$out"/ 2>/dev/null || true
  cp "$work"/*.jsonl "$work"/preview.* "$out"/ 2>/dev/null || true
}

case $phase in
  start)
    mkdir -p "$work"
    gpu_name
    t0=$(date +%s)
    synth_data "${DATA_SEED:-1000}" "${CLIPS:-600}" "${FRAMES:-64}" "$work/data"
    echo "synth: $(( $(date +%s) - t0 )) s, $(du -sh "$work/data" | cut -f1)"
    train dcae --seconds "${DCAE_SECONDS:-150}" --schedule-seconds "${DCAE_SECONDS:-150}" --batch 32 --lr 1e-3
    train encode
    train world --seconds "${WORLD_SECONDS:-240}" --schedule-seconds "${WORLD_SCHEDULE:-600}" \
      --batch "${BATCH:-32}" --lr 4e-4
    train preview --limit-clips 16
    ;;
  retrain)
    mkdir -p "$work"
    gpu_name
    t0=$(date +%s)
    synth_data "${DATA_SEED:-1002}" "${CLIPS:-350}" "${FRAMES:-48}" "$work/data"
    synth_data "${EXPLORE_SEED:-1003}" "${EXPLORE_CLIPS:-350}" "${FRAMES:-48}" "$work/explore" --explore
    echo "synth: $(( $(date +%s) - t0 )) s, $(du -sh "$work/data" "$work/explore" | cut -f1 | tr '\n' ' ')"
    train encode --init "${INIT:-models/small-synthetic}" --explore-data "$work/explore"
    train world --init "${INIT:-models/small-synthetic}" --seconds "${WORLD_SECONDS:-300}" \
      --schedule-seconds "${WORLD_SCHEDULE:-900}" --batch "${BATCH:-32}" --lr "${LR:-3e-4}" \
      --explore-share "${EXPLORE_SHARE:-0.5}"
    cp "${INIT:-models/small-synthetic}/weights_dcae.safetensors" "$work/small/"
    ;;
  resume)
    train world --seconds "${WORLD_SECONDS:-300}" --schedule-seconds "${WORLD_SCHEDULE:-600}" \
      --batch "${BATCH:-32}" --lr "${LR:-4e-4}" --explore-share "${EXPLORE_SHARE:-0.5}"
    [ -n "${SKIP_PREVIEW:-}" ] || train preview --limit-clips 16
    ;;
  *) echo "device_train.sh: start, resume or retrain" >&2; exit 2 ;;
esac
collect
