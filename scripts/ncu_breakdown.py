#!/usr/bin/env python3
"""Sums an ncu CSV (--csv --metrics gpu__time_duration.sum) by kernel kind.

Usage: scripts/ncu_breakdown.py NCU.csv
Kernels are grouped by kind from their names (products, attention, row norms, QK-norm + RoPE,
the rest by name), with each kind's launches, microseconds and share, then the ten longest
kernels. ncu times each kernel alone (caches flushed, clocks as found), so the sum is a
breakdown of the work, not the graph-replayed time.
"""
import csv
import sys
from collections import OrderedDict

KINDS = [  # (kind, substrings of the kernel name), first match wins
    ("products (cuBLASLt)", ("nvjet", "gemm", "cutlass", "sm90_xmma")),
    ("attention combine", ("combine_splits",)),
    ("attention", ("flash", "attention")),
    ("QK-norm + RoPE", ("qk_norm", "qk_rms", "rope")),
    ("row norms", ("row_norm", "layer_norm", "norm_modulate", "rms_norm", "gated")),
]


def kind_of(name):
    low = name.lower()
    for kind, keys in KINDS:
        if any(k in low for k in keys):
            return kind
    return "other: " + name.split("(")[0].split("<")[0].strip()[:60]


def rows(path):
    with open(path, newline="") as f:
        lines = [l for l in f if l.startswith('"')]
    for r in csv.DictReader(lines):
        if r.get("Metric Name") == "gpu__time_duration.sum":
            unit = r.get("Metric Unit", "nsecond")
            v = float(r["Metric Value"].replace(",", ""))
            scale = {"nsecond": 1e-3, "usecond": 1.0, "msecond": 1e3}.get(unit, 1e-3)
            yield r["Kernel Name"], v * scale


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    data = list(rows(sys.argv[1]))
    if not data:
        sys.exit(f"ncu_breakdown: no gpu__time_duration.sum rows in {sys.argv[1]}")
    sums = OrderedDict()
    for name, us in data:
        n, t = sums.get(kind_of(name), (0, 0.0))
        sums[kind_of(name)] = (n + 1, t + us)
    total = sum(t for _, t in sums.values())
    print(f"{len(data)} kernels, {total:.1f} us\n\n| kind | launches | us | share |\n|---|---:|---:|---:|")
    for k, (n, t) in sorted(sums.items(), key=lambda kv: -kv[1][1]):
        print(f"| {k} | {n} | {t:.1f} | {100 * t / total:.1f} % |")
    print("\nlongest kernels:")
    for name, us in sorted(data, key=lambda d: -d[1])[:10]:
        print(f"  {us:9.1f} us  {name[:110]}")


if __name__ == "__main__":
    main()
