#!/usr/bin/env bash
# Session 29, device call 5 (nvidia-h200): the rollout's DC-AE decode beside the next step
# (apps/epona/rollout_common.hpp FrameDecoder): the engine test, and bench_gpu_world's rollouts of
# 10 frames serial vs beside, official sampler and --sampler fast's midpoint x 10; then the Python
# module built on the machine and its tests (after the layering moves).
set -u
mkdir -p .device-build && tar xJf .devcalls/pkg.tar.xz -C .device-build
BIN=$PWD/.device-build/pkg OUT=$OUT/logs
source tests/cuda/device_env.sh
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/summary.txt"
b() { local n=$1; shift; local s=$(date +%s); timeout 400 "$@" > "$OUT/$n.out" 2> "$OUT/$n.err"; summary "$n rc=$? $(( $(date +%s) - s )) s $(grep -E 'assertions:' "$OUT/$n.out" | tail -1)"; }
b engine "$BIN/test_apps_engine_cuda" -s; grep -E "ERROR|FAILED" "$OUT/engine.out" | head -5
b rollout "$BIN/bench_gpu_world" --only step --repeats 6 --rollout-compare 10 --sampler-compare midpoint:10:10
grep -E "\"name\": \"(step|rollout)" "$OUT/rollout.out" | cut -c1-110 | tee -a "$OUT/summary.txt"
tail -3 "$OUT/rollout.err"
EPONA_DEVICE_DEPS=.devcalls/deps.tar.xz timeout 420 bash python/device_test.sh > "$OUT/python.log" 2>&1
summary "python rc=$? $(grep -E 'passed|failed' "$OUT/python.log" | tail -1)"
cd "$OUT" && tar cJf ../logs.tar.xz .
