#!/usr/bin/env python3
"""Where the bf16 error of the rollout's first waypoint comes from, in the official recipe.

Runs the official world model (through training/make_fixtures.py's compute()) on random models of
several sizes and seeds: once in float32 (the reference), then under bf16 autocast as the
official recipe does, and again with parts of it kept in float32: the TrajDiT, only its last
layer, the MST, or the MST and the TrajDiT. For each it writes the relative error (max abs error
over max |reference|, the manifest's measure) of the rollout tensors, for step 0 alone
(`name[0]`) and for the whole rollout. docs/world-model.md ("The planner in float32") has
the results of a run on an H200.

    python3 training/bf16_planner_sensitivity.py --official CHECKOUT --out results.json \
        [--sets a:5 b:9 ...]   # spec (training/other_sizes/<spec>.json) : seed

Needs a GPU (the recipe is CUDA autocast) and PyTorch.
"""
import argparse
import contextlib
import json
import os
import subprocess
import sys

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import make_fixtures as mf  # noqa: E402
import official  # noqa: E402

NAMES = ["rollout.rel_pose_after", "rollout.rel_yaw_after", "rollout.predict_traj", "rollout.stt_features"]
DEFAULT_SETS = "a:5 b:9 c:13 d:17 a:21 b:25 c:29 d:33 a:37 b:41 c:45 d:49".split()


def float32_call(fn, device):
    """fn run with autocast off and its floating-point tensor arguments in float32."""
    def run(*a, **k):
        cast = lambda v: v.float() if torch.is_tensor(v) and v.is_floating_point() else v  # noqa: E731
        with torch.autocast(device_type=device, enabled=False):
            return fn(*[cast(v) for v in a], **{n: cast(v) for n, v in k.items()})
    return run


@contextlib.contextmanager
def replaced(obj, name, wrap):
    original = getattr(obj, name)
    setattr(obj, name, wrap(original))
    try:
        yield
    finally:
        setattr(obj, name, original)


def variants(wm):
    """name -> the (object, method) pairs that run in float32 inside the bf16 recipe."""
    mst = [(wm.model, "evaluate"), (wm.model, "get_pose_emb")]
    return {"recipe": [], "traj_f32": [(wm.traj_dit, "forward")],
            "traj_last_layer_f32": [(wm.traj_dit.final_layer, "forward")],
            "mst_f32": mst, "mst_traj_f32": mst + [(wm.traj_dit, "forward")]}


def random_model(checkout, spec, seed, folder):
    if not os.path.exists(os.path.join(folder, "configs.json")):
        subprocess.run([sys.executable, os.path.join(HERE, "make_random_model.py"), "--official", checkout,
                        "--out", folder, "--spec", os.path.join(HERE, "other_sizes", spec + ".json"),
                        "--seed", str(seed), "--dtype", "float32"], check=True, capture_output=True)


def measure_set(off, checkout, spec, seed, device, work):
    folder = os.path.join(work, f"model_{spec}_{seed}")
    random_model(checkout, spec, seed, folder)
    configs = official.read_configs(os.path.join(folder, "configs.json"))
    s = mf.sizes(configs)
    wm, ae = mf.build_models(off, configs, folder, device, init_seed=seed)
    x = mf.random_inputs(s, seed)
    with torch.no_grad():
        ref = mf.compute(off, wm, ae, x, s, device)
    rows = []
    for name, parts in variants(wm).items():
        with contextlib.ExitStack() as stack, torch.no_grad():
            for obj, method in parts:
                stack.enter_context(replaced(obj, method, lambda fn: float32_call(fn, device)))
            out = mf.compute(off, wm, ae, x, s, device, world_ctx=mf.autocast(device), dcae_ctx=mf.tf32_default)
        row = {"set": f"{spec}:{seed}", "variant": name}
        for n in NAMES:
            row[n + "[0]"] = mf.measure(out[n][0], ref[n][0])["rel_max"]
            row[n] = mf.measure(out[n], ref[n])["rel_max"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--official", required=True, help="checkout of Kevin-thu/Epona")
    p.add_argument("--out", required=True, help="results (JSON)")
    p.add_argument("--sets", nargs="+", default=DEFAULT_SETS, help="spec:seed, spec from training/other_sizes/")
    p.add_argument("--work", default="/tmp/bf16_sensitivity", help="folder for the random models")
    a = p.parse_args()
    device = "cuda"
    mf.deterministic(device)
    off = official.load(a.official, device)
    mf.modern_linspace_for_old_torch(a.official)
    rows = []
    for entry in a.sets:
        spec, seed = entry.split(":")
        rows += measure_set(off, a.official, spec, int(seed), device, a.work)
    with open(a.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
