#!/usr/bin/env python3
"""A randomly initialised model folder (configs.json + weights_world / weights_dcae .safetensors) of
any size, built by the official constructors (training/official.py), for testing the fixture maker
and the C++ parity tests on sizes other than the public set's.

    /usr/bin/python3 training/make_random_model.py --official /work/epona-official --out DIR \
        [--spec training/small_epona.json] [--image-size 64 128] [--seed 3] [--dtype bfloat16|float32]

Sizes come from --spec (the layout of training/small_epona.json), --image-size overriding the
world-model frame (the DC-AE cases then use the same frame). As in the public set, the official
init is then perturbed so that no term is silent: linear/conv weights std 1/sqrt(fan_in), the MST
time embedding std 0.5, norm affines and BatchNorm statistics away from 1/0, the DC-AE temporal
blocks (zero-initialised by the official constructor) random.
"""
import argparse
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import official  # noqa: E402

TEMPLATE = os.path.join(official.ROOT, "tests", "data", "golden", "configs.json")


def perturb(module, g, time_emb_std=0.5):
    with torch.no_grad():
        for name, p in module.state_dict().items():
            if not p.is_floating_point():
                continue
            leaf = name.rsplit(".", 1)[-1]
            if name.endswith("time_emb"):
                p.copy_(torch.randn(p.shape, generator=g) * time_emb_std)
            elif leaf == "running_mean":
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)
            elif leaf == "running_var":
                p.copy_(1 + 0.3 * torch.rand(p.shape, generator=g))
            elif p.dim() >= 2:
                fan_in = p[0].numel()
                p.copy_(torch.randn(p.shape, generator=g) / fan_in ** 0.5)
            elif leaf in ("weight", "scale"):
                p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                p.copy_(0.1 * torch.randn(p.shape, generator=g))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--official", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--spec", default=os.path.join(official.HERE, "small_epona.json"))
    p.add_argument("--image-size", type=int, nargs=2)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--dtype", default="bfloat16", choices=["bfloat16", "float32"])
    p.add_argument("--set-name", default="random-small")
    a = p.parse_args()

    spec = official.read_configs(a.spec)
    wmc = dict(spec["world_model_config"])
    if a.image_size:
        wmc["image_size"] = list(a.image_size)
    d = spec["dcae"]
    configs = official.make_configs(TEMPLATE, wmc, d["width_list"], d["depth_list"], d["temporal_frames"], a.set_name)
    off = official.load(a.official, "cpu")
    torch.manual_seed(a.seed)
    wm = official.build_world(off, configs, "cpu")
    ae = official.build_dcae(off, configs, "cpu")
    g = torch.Generator().manual_seed(a.seed)
    perturb(wm, g)
    perturb(ae, g)
    dtype = getattr(torch, a.dtype)

    def cast(sd, prefix=""):
        return {prefix + k: (v.detach().to(dtype) if v.is_floating_point() else v.detach()).contiguous()
                for k, v in sd.items()}

    world = {}
    for part in ("model", "dit", "traj_dit"):
        world.update(cast(getattr(wm, part).state_dict(), f"module.{part}."))
    from safetensors.torch import save_file
    os.makedirs(a.out, exist_ok=True)
    meta = {"producer": "epona training/make_random_model.py", "set": a.set_name, "seed": str(a.seed)}
    save_file(world, os.path.join(a.out, "weights_world.safetensors"), metadata=meta)
    save_file(cast(ae.state_dict()), os.path.join(a.out, "weights_dcae.safetensors"), metadata=meta)
    with open(os.path.join(a.out, "configs.json"), "w") as f:
        json.dump(configs, f, indent=1)
    print(f"wrote {a.out}: {len(world)} world and {len(ae.state_dict())} DC-AE tensors ({a.dtype}), "
          f"image {configs['world_model_config']['image_size']}, set {a.set_name!r}")


if __name__ == "__main__":
    main()
