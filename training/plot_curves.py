#!/usr/bin/env python3
"""Plots the loss curves that training/train.py writes (dcae_loss.jsonl, world_loss.jsonl) into one
PNG for docs/training.md.

    python3 training/plot_curves.py training/runs/2026-11-27 docs/images/training-loss.png
"""
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def rows(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def smooth(values, k=9):
    out = []
    for i in range(len(values)):
        window = values[max(0, i - k // 2):i + k // 2 + 1]
        out.append(sum(window) / len(window))
    return out


def main():
    run, dest = sys.argv[1], sys.argv[2]
    dcae, world = rows(os.path.join(run, "dcae_loss.jsonl")), rows(os.path.join(run, "world_loss.jsonl"))
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    a.plot([r["step"] for r in dcae], [r["psnr"] for r in dcae], color="tab:blue", lw=1)
    a.set_xlabel("DC-AE step (batch 32)")
    a.set_ylabel("training-batch PSNR (dB)", color="tab:blue")
    a2 = a.twinx()
    a2.plot([r["step"] for r in dcae], [r["l1"] for r in dcae], color="tab:orange", lw=1)
    a2.set_ylabel("L1 (model range [-1, 1])", color="tab:orange")
    a.set_title("DC-AE f32c32 (3.1 M parameters)")
    steps = [r["step"] for r in world]
    b.plot(steps, smooth([r["loss_diff"] for r in world]), label="VisDiT velocity MSE", lw=1)
    b.plot(steps, smooth([r["loss_traj"] for r in world]), label="TrajDiT velocity MSE", lw=1)
    b.set_yscale("log")
    b.set_xlabel("world-model step (batch 32 windows of 10 frames)")
    b.set_ylabel("loss (running mean of 9 logged points)")
    b.set_title("MST + TrajDiT + VisDiT (7.9 M parameters)")
    b.legend()
    fig.tight_layout()
    fig.savefig(dest, dpi=110)
    print("wrote", dest)


if __name__ == "__main__":
    main()
