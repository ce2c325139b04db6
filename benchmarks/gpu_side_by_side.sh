#!/usr/bin/env bash
# Times the official Epona PyTorch implementation (its recipe: fp32 weights under bf16 autocast,
# DC-AE in float32 with TF32 convolutions) and epona (bf16) at the real configuration in one run
# on the same GPU, and prints one table: each row's median, the ratio official/epona, and the
# fraction of the bf16 roofline (compute-budget.md FLOPs / time, over the bf16 GEMM ceiling
# measured by bench_gpu_world through cuBLASLt).
# Usage: benchmarks/gpu_side_by_side.sh <official checkout> <dir with bench_gpu_world [bench_gpu_dcae]> [out dir]
# Programs print one JSON object per line: {"name", "ms", "runs"[, "tflop"]} or {"name", "value"}.
# The DC-AE rows of epona come from bench_gpu_dcae when it is there (rows dcae_decode,
# dcae_encode; the fastest bf16 row of each, its peak_mib); otherwise only PyTorch's are shown.
set -u
OFFICIAL=$(cd "$1" && pwd)
BIN=$(cd "$2" && pwd)
OUT=${3:-side-by-side-out}
source "$(dirname "$0")/../tests/cuda/device_env.sh"
HERE=$(cd "$(dirname "$0")" && pwd)

nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu,power.draw --format=csv | tee "$OUT/device.txt"
start=$(date +%s)
timeout "${EPONA_TIMEOUT:-420}" "$BIN/bench_gpu_world" --repeats "${EPONA_REPEATS:-10}" >"$OUT/epona.jsonl" 2>"$OUT/epona.err"
echo "bench_gpu_world rc=$? ($(( $(date +%s) - start )) s)"; grep '^#' "$OUT/epona.jsonl"; tail -3 "$OUT/epona.err"
if [ -x "$BIN/bench_gpu_dcae" ]; then
  timeout 200 "$BIN/bench_gpu_dcae" >"$OUT/dcae.jsonl" 2>"$OUT/dcae.err"
  echo "bench_gpu_dcae rc=$?"; tail -3 "$OUT/dcae.err"
fi
start=$(date +%s)
PYTHONUNBUFFERED=1 timeout "${OFFICIAL_TIMEOUT:-480}" python3 "$HERE/pytorch/official_bench.py" --official "$OFFICIAL" --repeats "${OFFICIAL_REPEATS:-5}" \
  >"$OUT/official.jsonl" 2>"$OUT/official.err"
echo "official_bench rc=$? ($(( $(date +%s) - start )) s)"; tail -3 "$OUT/official.err"

python3 - "$OUT" <<'PY'
import json, os, sys
out = sys.argv[1]
def load(name):
    rows = {}
    path = os.path.join(out, name)
    if os.path.exists(path):
        for line in open(path):
            line = line.strip()
            if line.startswith("{"):
                o = json.loads(line)
                rows[o["name"]] = o
    return rows
ep, off = load("epona.jsonl"), load("official.jsonl")
# bench_gpu_dcae prints several rows per name (dtype x convolution engine): the fastest bf16 one.
dcae_path, dcae_used = os.path.join(out, "dcae.jsonl"), {}
if os.path.exists(dcae_path):
    for line in open(dcae_path):
        if line.startswith("{"):
            o = json.loads(line)
            if o["name"] in ("dcae_decode", "dcae_encode") and o.get("dtype") == "bf16":
                if o["name"] not in ep or o["ms"] < ep[o["name"]]["ms"]:
                    ep[o["name"]] = o
                    dcae_used[o["name"]] = "%s/%s" % (o.get("dtype"), o.get("engine"))
if "dcae_decode" in ep and "peak_mib" in ep["dcae_decode"]:
    ep["dcae_device_memory_gib"] = {"value": ep["dcae_decode"]["peak_mib"] / 1024}
print("epona DC-AE rows:", dcae_used or "none (no bench_gpu_dcae output)")
ceiling = ep.get("gemm_tflops", {}).get("value", 0.0)
# FLOPs of the rows epona does not report itself (DC-AE: spec section 12 counting).
tflop = {k: v["tflop"] for k, v in ep.items() if "tflop" in v}
tflop.setdefault("dcae_decode", 5.5394)
tflop.setdefault("dcae_encode", 4.1709)
if "step" in ep and "dcae_decode" in ep:  # epona's step + decode: the two measured parts
    ep["step_decode"] = {"ms": ep["step"]["ms"] + ep["dcae_decode"]["ms"], "sum": True}
if "step" in tflop:
    tflop["step_decode"] = tflop["step"] + tflop["dcae_decode"]
labels = [("mst", "MST, 10 frames"), ("traj_eval", "TrajDiT one evaluation"), ("traj_sample", "TrajDiT 100-step sample"),
          ("vis_eval", "VisDiT one evaluation"), ("vis_sample", "VisDiT 100-step sample"),
          ("dcae_decode", "DC-AE decode, 1 frame"), ("dcae_encode", "DC-AE encode, 1 frame"),
          ("step", "AR step (MST + Traj 100 + Vis 100)"), ("step_decode", "AR step + decode")]
def frac(key, ms):
    if not ceiling or key not in tflop or not ms:
        return "-"
    return "%.1f%%" % (100 * tflop[key] / (ms * 1e-3) / ceiling)
print("\nbf16 GEMM ceiling (cuBLASLt 8192^3): %.0f TFLOP/s" % ceiling)
print("| %-36s | %10s | %10s | %8s | %8s | %8s | %8s |" % ("row", "PyTorch ms", "epona ms", "speed-up", "TFLOP", "PT roof", "ep roof"))
print("|" + "---|" * 7)
for key, label in labels:
    o = off.get(key, {}).get("ms")
    e = ep.get(key, {}).get("ms")
    note = " (sum)" if ep.get(key, {}).get("sum") else ""
    print("| %-36s | %10s | %10s | %8s | %8s | %8s | %8s |" % (
        label, "%.2f" % o if o else "-", ("%.2f" % e + note) if e else "-",
        "%.1fx" % (o / e) if o and e else "-", "%.2f" % tflop[key] if key in tflop else "-",
        frac(key, o), frac(key, e)))
pm = off.get("peak_memory_gib", {}).get("value")
em = ep.get("device_memory_gib", {}).get("value")
dm = ep.get("dcae_device_memory_gib", {}).get("value")
print("| %-36s | %10s | %10s | %8s |" % ("peak GPU memory (GiB)", "%.2f" % pm if pm else "-",
      ("%.2f" % (em + (dm or 0))) + ("" if dm else " (world model only)") if em else "-", "%.1fx" % (pm / (em + (dm or 0))) if pm and em else "-"))
PY
