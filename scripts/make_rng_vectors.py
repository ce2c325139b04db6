#!/usr/bin/python3
"""Reference vectors for epona::TorchGenerator (include/epona/core/rng.hpp).

Runs real PyTorch (Debian's torch 1.13: run with /usr/bin/python3) and records the float32 bit
patterns of torch.manual_seed(s); torch.randn(shape) for many sizes, seeds and multi-draw
sequences, once per CPU kernel PyTorch can pick for randn:
  randn_avx2.json     the AVX2 kernel (x86 CPUs with AVX2; PyTorch's usual choice)
  randn_generic.json  the generic kernel (ATEN_CPU_CAPABILITY=default, CPUs without AVX2)
Tensors of fewer than 16 elements take the same double-precision path under both; float64
randn draws of 15 elements ("normal_double", hex bit patterns) pin that path exactly.

Usage: /usr/bin/python3 scripts/make_rng_vectors.py [out_dir]   (default tests/data/rng)
"""
import json
import os
import subprocess
import sys

SEEDS = [0, 1, 42, 20250101, 2**32 + 5]
SIZES = list(range(1, 41)) + [100, 1000]
# Several draws from one generator: the state carries over, including the cached second
# normal of the double-precision path used below 16 elements.
SEQUENCES = [
    (0, [[3, 5], [20]]),
    (0, [[1], [1], [1], [3], [16], [1], [17], [2], [2, 3], [33], [1]]),
    (7, [[5], [40], [1], [15], [1, 8, 32], [2, 1, 15, 3], [1]]),
    (123, [[2, 2], [7], [7], [1000], [9]]),
]
KERNELS = {"avx2": None, "generic": "default"}  # name -> ATEN_CPU_CAPABILITY (None: PyTorch's choice)


def double_bits_of(t):
    import numpy as np
    return ["%016x" % int(b) for b in t.contiguous().numpy().view(np.uint64).ravel()]


def bits_of(t):
    import numpy as np
    return [int(b) for b in t.contiguous().numpy().view(np.uint32).ravel()]


def generate():
    import torch
    capability = [l for l in torch.__config__.show().splitlines() if "CPU capability" in l]
    cases = []
    for seed in SEEDS:
        for n in SIZES:
            torch.manual_seed(seed)
            cases.append({"seed": seed, "draws": [{"shape": [n], "bits": bits_of(torch.randn(n))}]})
    for seed, shapes in SEQUENCES:
        torch.manual_seed(seed)
        cases.append({"seed": seed, "draws": [{"shape": s, "bits": bits_of(torch.randn(*s))} for s in shapes]})
    # float64 randn of fewer than 16 elements: each element is one normal_distribution<double>
    # draw, uncast, so this pins the double-precision path (the float32 cast hides last bits).
    doubles = []
    for seed in SEEDS[:3]:
        torch.manual_seed(seed)
        draws = torch.cat([torch.randn(15, dtype=torch.float64) for _ in range(66)])
        doubles.append({"seed": seed, "hex": double_bits_of(draws)})
    return {"torch_version": torch.__version__,
            "normal_double": doubles,
            "cpu_capability": capability[0].split(":")[-1].strip() if capability else "?",
            "cases": cases}


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        json.dump(generate(), sys.stdout)
        return
    out_dir = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "tests", "data", "rng")
    os.makedirs(out_dir, exist_ok=True)
    for name, capability in KERNELS.items():
        env = dict(os.environ)
        env.pop("ATEN_CPU_CAPABILITY", None)
        if capability:
            env["ATEN_CPU_CAPABILITY"] = capability
        data = json.loads(subprocess.run([sys.executable, __file__, "--child"], env=env, check=True,
                                         capture_output=True, text=True).stdout)
        if name == "avx2" and data["cpu_capability"] not in ("AVX2", "AVX512"):
            sys.exit("this CPU/PyTorch does not use the AVX2 kernel (got %s)" % data["cpu_capability"])
        path = os.path.join(out_dir, "randn_%s.json" % name)
        with open(path, "w") as f:
            json.dump(data, f, separators=(",", ":"))
        print(path, data["torch_version"], data["cpu_capability"], len(data["cases"]), "cases")


if __name__ == "__main__":
    main()
