#!/usr/bin/env python3
"""Flow-solver quality sweep: `epona eval` for every solver x step count on one clip set.

For each setting it records planning L2 / collision rate and video PSNR / SSIM against the
ground truth (eval's own report), and the distance to the reference setting (100 Euler steps,
the official sampler): the planned waypoints' mean distance to the reference plan (metres) and
the PSNR of the generated frames against the reference's frames (dB; higher is closer). Every
setting draws the same noise (same seed per clip), so the distance is the solver's error alone.

Writes DIR/sweep.md (markdown table), DIR/sweep.json (all numbers), DIR/sweep.png (plot).
Reports already in DIR/runs/ are reused, so an interrupted sweep resumes.

  benchmarks/solver_sweep.py --epona build/apps/epona --clips clips/ --out sweep/ --horizon 2
"""
import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np
from PIL import Image

REFERENCE = ("euler", 100)
# The ODE's solution, as near as the sweep gets: the most accurate setting run (2nd order, most
# steps). Euler's errors at 50 and 100 steps point the same way, so "distance to 100 Euler steps"
# favours Euler; the distance to the solution does not.
CONVERGED = ("midpoint", 100)


def evaluations(solver, steps):
    """DiT evaluations per sample (flow::solver_evaluations)."""
    return {"heun": 2 * steps - 1, "midpoint": 2 * steps}.get(solver, steps)


def run_eval(a, solver, steps, run_dir):
    report = os.path.join(run_dir, f"{solver}_{steps}.json")
    frames = os.path.join(run_dir, f"{solver}_{steps}_frames")
    if os.path.exists(report):
        return report, frames, None
    cmd = [a.epona, "eval", "--clips", a.clips, "--json", report, "--solver", solver, "--steps", str(steps),
           "--horizon", str(a.horizon), "--seed", str(a.seed), "--threads", str(a.threads), "-q"]
    if a.limit:
        cmd += ["--limit", str(a.limit)]
    if a.no_video:
        cmd += ["--no-video"]
    else:
        cmd += ["--save-frames", frames]
    cmd += a.extra
    t0 = time.time()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return report, frames, time.time() - t0


def psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 100.0 if mse == 0 else min(100.0, 10 * math.log10(255.0 ** 2 / mse))


def plan_distance(r, ref):
    """Mean over clips of the mean (x, y) distance between the waypoints of two reports' plans."""
    d = []
    for c, c_ref in zip(r["per_clip"], ref["per_clip"]):
        if c["trajectory"] is None:
            continue
        p, q = np.array(c["trajectory"])[:, :2], np.array(c_ref["trajectory"])[:, :2]
        d.append(np.mean(np.linalg.norm(p - q, axis=1)))
    return float(np.mean(d)) if d else None


def video_distance(frames, ref_frames, r):
    """Mean PSNR of generated frames against the reference's, over clips and horizons."""
    if not os.path.isdir(frames):
        return None
    values = []
    for c in r["per_clip"]:
        clip_dir, ref_dir = os.path.join(frames, c["name"]), os.path.join(ref_frames, c["name"])
        if not os.path.isdir(clip_dir):
            continue
        for name in sorted(os.listdir(clip_dir)):
            a = np.asarray(Image.open(os.path.join(clip_dir, name)).convert("RGB"))
            b = np.asarray(Image.open(os.path.join(ref_dir, name)).convert("RGB"))
            values.append(psnr(a, b))
    return float(np.mean(values)) if values else None


def mean(v):
    v = [x for x in (v or []) if x is not None]
    return float(np.mean(v)) if v else None


def fmt(v, f="{:.3f}"):
    return "–" if v is None else f.format(v)


def table(rows, video):
    head = ("| solver | steps | DiT evals | L2 1 s (m) | L2 3 s (m) | coll. 3 s | plan to Euler-100 (m) "
            "| plan to solution (m) |")
    sep = "|---|---:|---:|---:|---:|---:|---:|---:|"
    if video:
        head += " PSNR (dB) | SSIM | video to Euler-100 (dB) | video to solution (dB) |"
        sep += "---:|---:|---:|---:|"
    lines = [head, sep]
    for r in rows:
        line = (f"| {r['solver']} | {r['steps']} | {r['evaluations']} | {fmt(r['l2_1s'])} | {fmt(r['l2_3s'])} | "
                f"{fmt(r['collision_rate'], '{:.2f}')} | {fmt(r['plan_to_ref'], '{:.4f}')} | "
                f"{fmt(r['plan_to_solution'], '{:.4f}')} |")
        if video:
            line += (f" {fmt(r['psnr'], '{:.2f}')} | {fmt(r['ssim'], '{:.4f}')} | {fmt(r['video_to_ref'], '{:.2f}')} | "
                     f"{fmt(r['video_to_solution'], '{:.2f}')} |")
        lines.append(line)
    return "\n".join(lines)


def plot(rows, path, video):
    try:
        import matplotlib
    except ImportError:
        print(f"solver_sweep: no matplotlib (Debian: python3-matplotlib), so {path} is not drawn", file=sys.stderr)
        return
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    panels = [("l2_3s", "planning L2 at 3 s (m)"), ("plan_to_ref", "plan: distance to 100 Euler (m)"),
              ("plan_to_solution", "plan: distance to solution (m)")]
    if video:
        panels += [("psnr", "video PSNR vs truth (dB)"), ("video_to_ref", "video: PSNR vs 100 Euler (dB)"),
                   ("video_to_solution", "video: PSNR vs solution (dB)")]
    cols = 3
    fig, axes = plt.subplots((len(panels) + cols - 1) // cols, cols, figsize=(4.4 * cols, 3.6 * ((len(panels) + cols - 1) // cols)))
    axes = np.atleast_1d(axes).ravel()
    for ax, (key, title) in zip(np.atleast_1d(axes), panels):
        for solver in dict.fromkeys(r["solver"] for r in rows):
            pts = [(r["evaluations"], r[key]) for r in rows if r["solver"] == solver and r[key] is not None
                   and not (key.endswith("to_ref") and (r["solver"], r["steps"]) == REFERENCE)
                   and not (key.endswith("to_solution") and (r["solver"], r["steps"]) == CONVERGED)]
            if pts:
                ax.plot(*zip(*pts), marker="o", label=solver)
        ax.set_xscale("log")
        ax.set_xlabel("DiT evaluations per sample")
        ax.set_title(title, fontsize=10)
        if key.startswith("plan_to"):
            ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--epona", required=True, help="the epona program")
    p.add_argument("--clips", required=True, help="clip set (epona synth --out)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--solvers", default="euler,heun,midpoint,dpmpp2m")
    p.add_argument("--steps", default="5,10,15,20,25,50,100")
    p.add_argument("--horizon", type=int, default=2)
    p.add_argument("--limit", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--no-video", action="store_true", help="planner only")
    p.add_argument("extra", nargs="*", help="more eval options after --, e.g. -- --backend cuda")
    a = p.parse_args()
    solvers = a.solvers.split(",")
    steps = [int(s) for s in a.steps.split(",")]
    for s in solvers:
        if s not in ("euler", "heun", "midpoint", "dpmpp2m"):
            sys.exit(f"solver_sweep: unknown solver '{s}'")
    if any(n < 1 or n > 100000 for n in steps):
        sys.exit("solver_sweep: steps must be in [1, 100000]")
    run_dir = os.path.join(a.out, "runs")
    os.makedirs(run_dir, exist_ok=True)

    settings = [REFERENCE] + [(s, n) for s in solvers for n in steps if (s, n) != REFERENCE]
    results = {}
    for solver, n in settings:
        report, frames, seconds = run_eval(a, solver, n, run_dir)
        with open(report) as f:
            results[(solver, n)] = (json.load(f), frames, seconds)
        print(f"{solver:9s} {n:4d} steps: {'reused' if seconds is None else f'{seconds:.0f} s'}", file=sys.stderr)

    ref, ref_frames, _ = results[REFERENCE]
    sol, sol_frames, _ = results.get(CONVERGED, (None, None, None))
    rows = []
    for solver, n in sorted(settings, key=lambda k: (solvers.index(k[0]), k[1])):
        r, frames, seconds = results[(solver, n)]
        m = r["model"]
        rows.append({"solver": solver, "steps": n, "evaluations": evaluations(solver, n),
                     "l2_1s": m.get("l2_1s"), "l2_3s": m.get("l2_3s"), "collision_rate": m.get("collision_rate"),
                     "psnr": mean(m.get("psnr")), "ssim": mean(m.get("ssim")),
                     "plan_to_ref": plan_distance(r, ref),
                     "video_to_ref": None if a.no_video else video_distance(frames, ref_frames, r),
                     "plan_to_solution": plan_distance(r, sol) if sol else None,
                     "video_to_solution": None if a.no_video or not sol else video_distance(frames, sol_frames, r),
                     "seconds": seconds})
    video = not a.no_video
    clips = ref["clips"]
    md = (f"Solver sweep: {clips} clip(s) from {a.clips}, seed {a.seed} + clip index, "
          f"{'planner only' if a.no_video else f'video horizons 1..{a.horizon}'}; references: 100 Euler steps "
          f"and the ODE's solution (midpoint, 100 steps).\n\n"
          + table(rows, video) + "\n")
    with open(os.path.join(a.out, "sweep.md"), "w") as f:
        f.write(md)
    with open(os.path.join(a.out, "sweep.json"), "w") as f:
        json.dump({"clips": clips, "clips_dir": a.clips, "horizon": a.horizon, "video": video, "rows": rows}, f, indent=1)
    plot(rows, os.path.join(a.out, "sweep.png"), video)
    print(md)


if __name__ == "__main__":
    main()
