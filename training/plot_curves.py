#!/usr/bin/env python3
"""Plots the loss curves that training/train.py writes (dcae_loss.jsonl, world_loss.jsonl) into one
PNG for docs/training.md.

    python3 training/plot_curves.py training/runs/2026-11-27 docs/images/training-loss.png
    python3 training/plot_curves.py --run2 training/runs/2026-11-28 docs/images/training-loss-run2.png
    python3 training/plot_curves.py --chunks "Run 4: from run 2's weights, 840 s" \
        docs/images/training-loss-run4.png training/runs/2026-11-28-run4/world_loss.jsonl

--run2 plots the second run (two chunks from the first run's weights, natural and exploring-driver
batches, lambda_yaw_pose 2): world_loss_chunk1.jsonl then world_loss_chunk2.jsonl. --chunks plots
any run of that kind from its world-model loss files, one per chunk, in order.
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


def plot_chunks(files, dest, title, trajectory_weight=2.0):
    chunks = [rows(f) for f in files]
    world, offset = [], 0
    for chunk in chunks:
        world += [dict(r, step=r["step"] + offset) for r in chunk]
        offset += chunk[-1]["step"]
    natural = [r for r in world if not r.get("exploring")]
    exploring = [r for r in world if r.get("exploring")]
    fig, ax = plt.subplots(figsize=(7, 3.8))
    ax.plot([r["step"] for r in natural], smooth([r["loss_diff"] for r in natural]), label="VisDiT, natural batches", lw=1)
    ax.plot([r["step"] for r in exploring], smooth([r["loss_diff"] for r in exploring]), label="VisDiT, exploring-driver batches", lw=1)
    ax.plot([r["step"] for r in natural], smooth([r["loss_traj"] / trajectory_weight for r in natural]),
            label="TrajDiT (natural batches only)", lw=1)
    ends = [c[-1]["step"] for c in chunks]
    for end in [sum(ends[:i + 1]) for i in range(len(ends) - 1)]:
        ax.axvline(end, color="grey", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_xlabel("world-model step (batch 48)" + ("; dashed: next chunk, fresh optimiser" if len(ends) > 1 else ""))
    ax.set_ylabel("velocity MSE (running mean of 9 logged points)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(dest, dpi=110)
    print("wrote", dest)


def main():
    if sys.argv[1] == "--run2":
        files = [os.path.join(sys.argv[2], f"world_loss_chunk{i}.jsonl") for i in (1, 2)]
        return plot_chunks(files, sys.argv[3], "Run 2: from run 1's weights, natural + exploring-driver drives")
    if sys.argv[1] == "--chunks":
        return plot_chunks(sys.argv[4:], sys.argv[3], sys.argv[2])
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
