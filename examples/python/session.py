# %% [markdown]
# # A driving session with the bundled model
#
# `epona.WorldSession` keeps the world model loaded and the window of the last F frames: each
# `step()` plans (or takes your action), draws the next frame and slides the window. This runs a
# few steps of the bundled model (models/small-synthetic, 256x512) on its demo clip and writes the
# frames side by side as a PNG. Build the module first (docs/python.md), then:
#
#     PYTHONPATH=build/python /usr/bin/python3 examples/python/session.py [OUT.png] [--steps N]
#
# `--steps` sets each DiT's sampling steps (the model's 100 take a few seconds a frame on 2 cores).

# %%
import argparse
import time
from pathlib import Path

import numpy as np

import epona

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("out", nargs="?", default="out/python_session.png")
parser.add_argument("--steps", type=int, default=20, help="sampling steps of each DiT")
parser.add_argument("--frames", type=int, default=4, help="steps to take")
args = parser.parse_args()

# %% Load the bundled model (the same loader as `epona plan` without --weights).
model = epona.load()
demo = Path(epona.bundled_model_dir) / "demo"
F = model.condition_frames
files = sorted((demo / "frames").glob("*.png"))[-F:]
frames = np.stack([epona.read_image(str(f)) for f in files])  # (F, H, W, 3) uint8
poses = epona.load_poses(str(demo / "poses.csv"))[-F:]        # (F, 3): x m, y m, yaw deg
print(f"model: {model.image_size[0]}x{model.image_size[1]} frames, window of {F}, from {model.world_file}")

# %% Start a session: the window is encoded once.
session = epona.WorldSession(model, steps=args.steps, seed=0)
session.reset(frames, poses)

# %% Step: the model's own plan first, then an action of ours (2 m ahead, a slight left turn).
generated = []
for i in range(args.frames):
    action = None if i % 2 == 0 else (2.0, 0.0, 2.0)
    t0 = time.perf_counter()
    frame, plan = session.step(action)
    took = time.perf_counter() - t0
    generated.append(frame)
    if plan is not None:
        print(f"step {i}: planned, waypoint 0 = ({plan[0, 0]:.2f} m, {plan[0, 1]:.2f} m, {plan[0, 2]:.2f} deg), "
              f"3 s ahead = ({plan[-1, 0]:.1f} m, {plan[-1, 1]:.1f} m); {took:.1f} s")
    else:
        print(f"step {i}: drove the given action {action}; {took:.1f} s")

# %% The window now ends with the generated frames and the motions that led to them.
latents, motions = session.window()
print("window motions (x, y, yaw), oldest first:\n", np.round(motions, 2))

# %% Write the last input frame and the generated ones side by side.
strip = np.concatenate([frames[-1]] + generated, axis=1)
Path(args.out).parent.mkdir(parents=True, exist_ok=True)
epona.write_png(args.out, strip)
print(f"wrote {args.out} ({strip.shape[0]}x{strip.shape[1]}: the last input frame, then {len(generated)} generated)")
