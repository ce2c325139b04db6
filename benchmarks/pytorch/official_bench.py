#!/usr/bin/env python3
"""Times the official Epona PyTorch implementation the way its test scripts run it.

The side-by-side harness (benchmarks/gpu_side_by_side.sh) runs this and epona's own benchmark in
one session on the same machine and prints the ratios. This file contains none of the official
code: it imports it from the checkout given with --official.

Recipe (../shared/spec/pytorch-baseline.md): float32 weights; MST, TrajDiT and VisDiT under
torch.autocast(bfloat16); the DC-AE in float32 outside autocast with PyTorch's default TF32
convolutions and cudnn.benchmark. Random weights (official initialisation; the DC-AE's
zero-initialised temporal blocks get random weights). CUDA events around each call after
warm-up, medians. On the CPU (--device cpu) everything runs in float32 with the given thread
count; the Triton RMSNorm2d kernel is replaced by its formula there (Triton needs a GPU).

Prints one JSON object per line: {"name": ..., "ms": median, "runs": [...]} and, on the GPU,
{"name": "peak_memory_gib", "value": ...}. "gemm2048" (a float32 2048³ torch.mm outside autocast,
the ceiling the CPU baseline quotes) runs only when named in --only.
"""
import argparse
import json
import os
import runpy
import statistics
import sys
import time
import types

import torch

HERE = os.path.dirname(os.path.abspath(__file__))

BENCH_MID = dict(image_size=(256, 512), n_embd=1024, n_head=8, n_layer=[4, 2, 2], n_embd_dit=1024,
                 n_head_dit=8, n_embd_dit_traj=512, n_head_dit_traj=4)


def parse_args():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--official", required=True, help="path to a checkout of Kevin-thu/Epona")
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    ap.add_argument("--config", choices=["real", "bench-mid"], default="real")
    ap.add_argument("--threads", type=int, default=0, help="CPU threads (0: PyTorch default)")
    ap.add_argument("--steps", type=int, default=100, help="sampling steps")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--only", default="", help="comma-separated subset of measurement names")
    ap.add_argument("--dcae-size", default="", help="HxW of the DC-AE benchmark image (default: the config's)")
    return ap.parse_args()


def load_official(path, device):
    sys.path.insert(0, HERE)  # the omegaconf stand-in
    sys.path.insert(0, os.path.abspath(path))
    if device == "cpu":
        # The official constructors call .cuda() unconditionally.
        torch.nn.Module.cuda = lambda self, *a, **k: self
        torch.Tensor.cuda = lambda self, *a, **k: self
    from models.model import TrainTransformersDiT  # noqa: E402
    from models.modules import dcae as dcae_module  # noqa: E402
    from models.modules.sampling import get_schedule, prepare_ids  # noqa: E402
    from models.modules.tokenizer import poses_to_indices, yaws_to_indices  # noqa: E402
    if device == "cpu":
        patch_triton_rmsnorm()
        import models.modules.sampling as sampling  # prepare_ids defaults to device="cuda"
        sampling.prepare_ids.__defaults__ = ("cpu",)
    return types.SimpleNamespace(TrainTransformersDiT=TrainTransformersDiT, dcae=dcae_module,
                                 get_schedule=get_schedule, prepare_ids=prepare_ids,
                                 poses_to_indices=poses_to_indices, yaws_to_indices=yaws_to_indices)


def patch_triton_rmsnorm():
    from models.modules.dcae_layers import norm

    def forward(self, x):  # RMSNorm2d: per pixel over channels, then weight and bias
        r = torch.rsqrt(x.float().pow(2).mean(dim=1, keepdim=True) + self.eps)
        return (x * r) * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)

    norm.TritonRMSNorm2d.forward = forward


def model_args(path, config):
    cfg = runpy.run_path(os.path.join(path, "configs", "dit_config_dcae_nuplan.py"))
    cfg = {k: v for k, v in cfg.items() if not k.startswith("__")}
    if config == "bench-mid":
        cfg.update(BENCH_MID)
    cfg.setdefault("batch_size", 1)  # a command-line option of the official scripts (default 1), not in the config
    return types.SimpleNamespace(**cfg)


class Timer:
    def __init__(self, device):
        self.device = device

    def measure(self, fn, repeats, warmup):
        for _ in range(warmup):
            fn()
        runs = []
        for _ in range(repeats):
            if self.device == "cuda":
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                torch.cuda.synchronize()
                start.record()
                fn()
                end.record()
                torch.cuda.synchronize()
                runs.append(start.elapsed_time(end))
            else:
                t0 = time.perf_counter()
                fn()
                runs.append((time.perf_counter() - t0) * 1e3)
        return runs


def emit(name, runs):
    print(json.dumps({"name": name, "ms": statistics.median(runs), "runs": runs}), flush=True)


def build_dcae(off, args, device, token_size):
    cfg = off.dcae.dc_ae_f32c32("dc-ae-f32c32-mix-1.0", add_encoder_temporal=False,
                                add_decoder_temporal=True, condition_frames=args.temporal_patch_size,
                                token_size=token_size)
    ae = off.dcae.DCAE(cfg).to(device).eval()
    with torch.no_grad():  # the official constructor zero-initialises the temporal blocks
        for name, p in ae.named_parameters():
            if name.startswith(("causal_time_block", "space_block")):
                p.normal_(0, 0.02)
    return ae


def main():
    a = parse_args()
    dev = a.device
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    if dev == "cuda":
        torch.backends.cudnn.benchmark = True  # as the official scripts
    off = load_official(a.official, dev)
    args = model_args(a.official, a.config)
    args.num_sampling_steps = a.steps
    only = set(filter(None, a.only.split(",")))
    want = lambda n: not only or n in only  # noqa: E731
    timer = Timer(dev)
    torch.manual_seed(0)

    wm = off.TrainTransformersDiT(args, local_rank=0, condition_frames=args.condition_frames).to(dev).eval()
    F, traj_len = args.condition_frames, args.traj_len
    h, w = args.image_size[0] // 32, args.image_size[1] // 32
    L = h * w
    latents = torch.randn(1, F, L, args.vae_embed_dim, device=dev)
    rel_pose = torch.rand(1, F + 1, 2, device=dev) * torch.tensor([4.0, 0.2], device=dev)
    rel_yaw = (torch.rand(1, F + 1, 1, device=dev) - 0.5) * 4
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if dev == "cuda" else \
        (lambda: torch.autocast("cpu", enabled=False))

    with torch.no_grad():
        pose_idx = off.poses_to_indices(rel_pose, args.pose_x_vocab_size, args.pose_y_vocab_size)
        yaw_idx = off.yaws_to_indices(rel_yaw, args.yaw_vocab_size)
        with autocast():
            cond, pose_emb = wm.model.evaluate(latents, pose_idx, yaw_idx, sample_last=True)
        img_ids, cond_ids, traj_ids = off.prepare_ids(1, h, w, L + 3, traj_len)
        img_ids, cond_ids, traj_ids = img_ids.to(dev), cond_ids.to(dev), traj_ids.to(dev)
        x_traj = torch.randn(1, traj_len, 3, device=dev)
        x_img = torch.randn(1, L, args.vae_embed_dim, device=dev)
        t = torch.full((1,), 0.3, device=dev)
        sched_traj = off.get_schedule(a.steps, traj_len)
        sched_img = off.get_schedule(a.steps, L)

        def run(name, fn, repeats=a.repeats):
            if want(name):
                try:
                    with autocast():
                        emit(name, timer.measure(fn, repeats, a.warmup))
                except Exception as e:  # one failing row must not hide the others
                    print(json.dumps({"name": name, "error": repr(e)}), flush=True)

        run("mst", lambda: wm.model.evaluate(latents, pose_idx, yaw_idx, sample_last=True))
        run("traj_eval", lambda: wm.traj_dit(x_traj, traj_ids, cond, cond_ids, t))
        run("traj_sample", lambda: wm.traj_dit.sample(x_traj, traj_ids, cond, cond_ids, sched_traj),
            max(1, a.repeats // 2))
        run("vis_eval", lambda: wm.dit(x_img, img_ids, cond, cond_ids, t, pose_emb))
        run("vis_sample", lambda: wm.dit.sample(x_img, img_ids, cond, cond_ids, pose_emb, sched_img),
            max(1, a.repeats // 2))

        if "gemm2048" in only:  # the float32 GEMM ceiling (pytorch-baseline.md); only when asked for by name
            a_mat, b_mat = torch.randn(2048, 2048, device=dev), torch.randn(2048, 2048, device=dev)
            emit("gemm2048", timer.measure(lambda: torch.mm(a_mat, b_mat), a.repeats, a.warmup))

        need_ae = any(want(n) for n in ("dcae_decode", "dcae_encode", "step_decode"))
        if need_ae:
            if a.dcae_size:
                H, W = (int(v) for v in a.dcae_size.lower().split("x"))
            else:
                H, W = args.image_size
            ae = build_dcae(off, args, dev, (H // 32) * (W // 32))
            z = torch.randn(1, 32, H // 32, W // 32, device=dev)
            img = torch.rand(1, 3, H, W, device=dev) * 2 - 1
            if want("dcae_decode"):
                emit("dcae_decode", timer.measure(lambda: ae.decode(z, is_video=False), a.repeats, a.warmup))
            if want("dcae_encode"):
                emit("dcae_encode", timer.measure(lambda: ae.encode(img), a.repeats, a.warmup))

        devnull = open(os.devnull, "w")

        def quiet(fn):  # step_eval prints unsynchronised timings
            stdout, sys.stdout = sys.stdout, devnull
            try:
                return fn()
            finally:
                sys.stdout = stdout

        def step():
            with torch.autocast("cuda", dtype=torch.bfloat16):
                return wm.step_eval(latents, rel_pose, rel_yaw, self_pred_traj=True)

        if want("step") and dev == "cuda":
            emit("step", quiet(lambda: timer.measure(step, max(1, a.repeats // 2), 1)))

        if want("step_decode") and dev == "cuda":
            def step_decode():
                _, lat = step()
                frame = ae.decode(lat.permute(0, 3, 1, 2).float(), is_video=False)  # z_to_image's layout
                return (frame / 2 + 0.5).clamp(0, 1)

            torch.cuda.reset_peak_memory_stats()
            runs = quiet(lambda: timer.measure(step_decode, max(1, a.repeats // 2), 1))
            emit("step_decode", runs)
            print(json.dumps({"name": "peak_memory_gib",
                              "value": torch.cuda.max_memory_allocated() / 2**30}), flush=True)


if __name__ == "__main__":
    main()
