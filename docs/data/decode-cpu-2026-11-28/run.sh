#!/usr/bin/env bash
# Session 28: the CPU DC-AE decode (128x256, float32, 2 threads) of epona and of the official
# PyTorch code on this machine's CPU, alternated twice (PyTorch, epona, PyTorch, epona), 15 timed
# calls each after 2 warm-ups (issue #36: settle whether epona is faster).
set -u
D=$OUT/decode_cpu; mkdir -p "$D"
grep -m1 'model name' /proc/cpuinfo | tee "$D/machine.txt"; nproc | tee -a "$D/machine.txt"
for round in 1 2; do
  CUDA_VISIBLE_DEVICES= OMP_NUM_THREADS=2 timeout 150 python3 benchmarks/pytorch/official_bench.py --official .official \
    --device cpu --config bench-mid --threads 2 --dcae-size 128x256 --only dcae_decode --repeats 15 --warmup 2 \
    > "$D/pytorch_$round.jsonl" 2> "$D/pytorch_$round.log"; echo "pytorch round $round rc=$?"
  timeout 150 .devcalls/bench_cpu_bench_mid --threads 2 --calls dcae_decode --weights f32 --dcae-size 128x256 \
    --repeats 15 --warmup 2 > "$D/epona_$round.jsonl" 2> "$D/epona_$round.log"; echo "epona round $round rc=$?"
  cat "$D/pytorch_$round.jsonl" "$D/epona_$round.jsonl" | cut -c1-200
done
