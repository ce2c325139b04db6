#!/usr/bin/env python3
"""Compares two golden-format sets tensor by tensor: rel_max = max|A - B| / max|B| (B is the reference).

    /usr/bin/python3 training/compare_cases.py A B [--limit 1e-4] [--rollout-limit 1e-3]

A and B are folders holding cases.safetensors (or the files themselves). Prints one line per tensor
(inputs marked; they should be identical when A was made with --inputs-from B) and exits 1 when a
tensor is missing, differs in shape, is not finite, or exceeds its limit: `--limit` for every output,
`--rollout-limit` for rollout.*, 0 for inputs, 1e-6 for ids.*, sched.* and the token indices.
"""
import argparse
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import official  # noqa: E402

official._add_stand_ins()
import torch  # noqa: E402
from safetensors.torch import load_file  # noqa: E402


def cases_path(p):
    return os.path.join(p, "cases.safetensors") if os.path.isdir(p) else p


def roles(p):
    m = os.path.join(p if os.path.isdir(p) else os.path.dirname(p), "manifest.json")
    if not os.path.exists(m):
        return {}
    return {k: v.get("role", "") for k, v in json.load(open(m)).get("tensors", {}).items()}


def limit_for(name, role, a):
    if role == "input":
        return 0.0
    if name.startswith(("ids.", "sched.", "tok.")) or name in ("mst.pose_idx", "mst.yaw_idx"):
        return 1e-6
    if name.startswith("rollout."):
        return a.rollout_limit
    return a.limit


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a")
    p.add_argument("b", help="the reference")
    p.add_argument("--limit", type=float, default=1e-4)
    p.add_argument("--rollout-limit", type=float, default=1e-3)
    a = p.parse_args()
    A, B = load_file(cases_path(a.a)), load_file(cases_path(a.b))
    role = roles(a.b) or roles(a.a)
    failed = []
    worst = {"input": 0.0, "output": 0.0, "rollout": 0.0}
    print(f"{'tensor':32s} {'role':6s} {'shape':22s} {'rel_max':>10s} {'max_abs':>10s} {'limit':>8s}")
    for name in sorted(set(A) | set(B), key=lambda k: (list(B).index(k) if k in B else 1e9, k)):
        r = role.get(name, "?")
        if name not in A or name not in B:
            print(f"{name:32s} {r:6s} missing in {'A' if name not in A else 'B'}")
            failed.append(name)
            continue
        x, y = A[name].double(), B[name].double()
        if x.shape != y.shape:
            print(f"{name:32s} {r:6s} shape {list(x.shape)} vs {list(y.shape)}")
            failed.append(name)
            continue
        finite = bool(torch.isfinite(x).all())
        diff = float((x - y).abs().max()) if x.numel() else 0.0
        ref = float(y.abs().max()) if y.numel() else 0.0
        rel = diff / ref if ref > 0 else (0.0 if diff == 0 else math.inf)
        lim = limit_for(name, r, a)
        bad = not finite or not rel <= lim
        kind = "input" if r == "input" else ("rollout" if name.startswith("rollout.") else "output")
        worst[kind] = max(worst[kind], rel)
        print(f"{name:32s} {r:6s} {str(list(y.shape)):22s} {rel:10.3e} {diff:10.3e} {lim:8.0e}"
              f"{'  NOT FINITE' if not finite else ''}{'  FAIL' if bad else ''}")
        if bad:
            failed.append(name)
    print(f"worst rel_max: inputs {worst['input']:.3e}, outputs outside the rollout {worst['output']:.3e}, "
          f"rollout {worst['rollout']:.3e}")
    if failed:
        print(f"{len(failed)} tensor(s) failed: {', '.join(failed)}")
        sys.exit(1)
    print("all tensors within their limits")


if __name__ == "__main__":
    main()
