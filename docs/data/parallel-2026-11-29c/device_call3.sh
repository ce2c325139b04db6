#!/usr/bin/env bash
# Session 37, call 3 (nvidia-h200-x2): after the fix of the float path's copy (call 2: the push moved
# 16 of a float pack's 32 bytes; bf16 was right). The peer group's tests, the DiT over it, the
# VisDiT and AR-step rows through both groups (the peer kernel at 64 and 128 blocks), and the
# program's --tensor-parallel 2 through both against the whole model, frames compared pixel by pixel.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c3
source tests/cuda/device_env.sh
nccl=$(find /usr/lib /usr/local -name 'libnccl.so.2' 2>/dev/null | head -1)
[ -n "$nccl" ] && export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$(dirname "$nccl")"
export NCCL_NVLS_ENABLE=0
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
for t in test_cuda_peer_shard_sum test_cuda_dit_shards; do
  start=$(date +%s%N)
  timeout 300 $BIN/$t > $OUT/$t.log 2>&1
  summary "$t rc=$? $(elapsed $start) $(grep -h 'test cases:' $OUT/$t.log) $(grep -h 'assertions:' $OUT/$t.log)"
  grep -h "no progress\|ERROR\|skipping\|logged" $OUT/$t.log | sort | uniq -c | head -12 | tee -a $OUT/summary.txt
done
M=$PWD/models/small-synthetic
common="--weights $M/weights_world.safetensors --dcae $M/weights_dcae.safetensors --config $M/configs.json --frames $M/demo/frames --poses $M/demo/poses.csv --backend cuda -n 3"
for run in "tp1:--tensor-parallel 1" "peer:--tensor-parallel 2 --shard-sum peer" "nccl:--tensor-parallel 2 --shard-sum nccl" "auto:--tensor-parallel 2" "peer_bf16:--tensor-parallel 2 --dtype bf16" "tp1_bf16:--dtype bf16"; do
  name=${run%%:*}; flags=${run#*:}
  start=$(date +%s%N)
  timeout 60 $BIN/epona generate $common $flags --out $OUT/gen_$name > $OUT/gen_$name.log 2>&1
  summary "generate $name rc=$? $(elapsed $start) $(grep -h 'VisDiT split\|epona:' $OUT/gen_$name.log | head -1 | cut -c1-150)"
done
python3 - "$OUT" <<'PY' | tee -a $OUT/summary.txt
import json, sys, zlib, struct, glob, os
import numpy as np
o = sys.argv[1]
cache = {}
def png(path):  # 8-bit RGB/RGBA PNG, as stb writes it
    if path in cache: return cache[path]
    data = open(path, "rb").read(); pos = 8; idat = b""
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8]); body = data[pos + 8:pos + 8 + n]; pos += 12 + n
        if kind == b"IHDR": w, h, depth, color = struct.unpack(">IIBB", body[:10])
        if kind == b"IDAT": idat += body
    ch = {2: 3, 6: 4, 0: 1}[color]; raw = zlib.decompress(idat); stride = w * ch
    img = np.zeros((h, stride), np.int32); prev = np.zeros(stride, np.int32)
    for y in range(h):
        f = raw[y * (stride + 1)]; line = np.frombuffer(raw, np.uint8, stride, y * (stride + 1) + 1).astype(np.int32)
        out = np.zeros(stride, np.int32)
        for x in range(stride):
            a = out[x - ch] if x >= ch else 0; b = prev[x]; c = prev[x - ch] if x >= ch else 0
            if f == 0: p = 0
            elif f == 1: p = a
            elif f == 2: p = b
            elif f == 3: p = (a + b) // 2
            else:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                p = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            out[x] = (line[x] + p) & 255
        img[y] = out; prev = out
    cache[path] = img
    return img
def nums(x):
    if isinstance(x, dict): return [v for k in sorted(x) for v in nums(x[k])]
    if isinstance(x, list): return [v for e in x for v in nums(e)]
    return [x] if isinstance(x, (int, float)) and not isinstance(x, bool) else []
for name, base in [("peer", "tp1"), ("nccl", "tp1"), ("peer_bf16", "tp1_bf16")]:
    try:
        ta = nums(json.load(open(f"{o}/gen_{name}/trajectory.json"))); tb = nums(json.load(open(f"{o}/gen_{base}/trajectory.json")))
        plan = max(abs(x - y) for x, y in zip(ta, tb))
        frames = []
        for f in sorted(glob.glob(f"{o}/gen_{base}/frames/*.png")):
            a = png(f); b = png(f"{o}/gen_{name}/frames/{os.path.basename(f)}")
            d = np.abs(a - b); frames.append(f"{os.path.basename(f)}: max {d.max()}, mean {d.mean():.4f}, differing {np.count_nonzero(d) / d.size:.4%}")
        print(f"{name} vs {base}: plans max abs {plan:.3g}; " + "; ".join(frames))
    except Exception as e:
        print(f"{name} vs {base}: {e}")
PY
rm -rf $OUT/gen_*/frames $OUT/gen_*/*.png
for b in 64 128; do
  timeout 100 $BIN/bench_gpu_shards --only vis --repeats 5 --peer-blocks $b > $OUT/bench_vis_b$b.txt 2>&1; summary "bench vis blocks $b rc=$?"; grep peer2\\\|nccl2\\\|whole\\\|alone $OUT/bench_vis_b$b.txt | tee -a $OUT/summary.txt
done
timeout 150 $BIN/bench_gpu_shards --only step --repeats 5 --peer-blocks 128 > $OUT/bench_step.txt 2>&1; summary "bench step rc=$?"; cat $OUT/bench_step.txt | tee -a $OUT/summary.txt
