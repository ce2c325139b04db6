#!/usr/bin/env python3
"""Trains the small Epona of docs/training.md on clips of the synthetic world (`epona synth --format npy`).

Stages, each a subcommand, each resumable from its output folder:

  dcae   the DC-AE f32c32 (official architecture, widths of training/small_epona.json) as an
         autoencoder: L1 + MSE reconstruction, a latent-statistics penalty that keeps the latent
         near zero mean and unit variance (the rectified flow starts from N(0, 1) noise and the
         official pipeline applies no latent scaling), and noise on the latent seen by the decoder
  world  MST + TrajDiT + VisDiT with the official losses (TrainTransformersDiT.step_train: the
         rectified-flow velocity MSE of both DiTs) and the official chain-of-forward (every
         `multifw_perstep` steps, `forward_iter` passes that feed the model's own one-step
         predictions back as the next window), on latents of the frozen DC-AE
  export bf16 weights in the layout epona loads (weights_world / weights_dcae .safetensors +
         configs.json), the models/small folder

All stages take --official (a checkout of Kevin-thu/Epona: the model code is imported from it,
none is copied) and --work (the folder holding checkpoints, logs and the latent cache).
"""
import argparse
import contextlib
import glob
import json
import math
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import official  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
TEMPLATE = os.path.join(official.ROOT, "tests", "data", "golden", "configs.json")


def log(*a):
    print(time.strftime("%H:%M:%S"), *a, flush=True)


def model_configs(path):
    spec = official.read_configs(path)
    d = spec["dcae"]
    return official.make_configs(TEMPLATE, spec["world_model_config"], d["width_list"], d["depth_list"],
                                 d["temporal_frames"], "small-epona")


# ---------------------------------------------------------------------------------------- data

def load_clips(folder, device, limit=0):
    """Every clip_*/frames.npy (T, H, W, 3 uint8) and poses_abs.npy (T', 3: x, y, yaw rad)."""
    dirs = sorted(glob.glob(os.path.join(folder, "clip_*")))
    if limit:
        dirs = dirs[:limit]
    if not dirs:
        raise SystemExit(f"no clip_* folders in {folder}")
    frames = [np.load(os.path.join(d, "frames.npy")) for d in dirs]
    poses = [np.load(os.path.join(d, "poses_abs.npy")) for d in dirs]
    t_frames = min(f.shape[0] for f in frames)
    t_poses = min(p.shape[0] for p in poses)
    frames = torch.from_numpy(np.stack([f[:t_frames] for f in frames])).to(device)  # (N, T, H, W, 3)
    poses = torch.from_numpy(np.stack([p[:t_poses] for p in poses])).double().to(device)
    log(f"loaded {len(dirs)} clips of {t_frames} frames ({tuple(frames.shape[2:4])}) and {t_poses} poses")
    return frames, poses


def to_model_range(u8):  # (..., H, W, 3) uint8 -> (..., 3, H, W) in [-1, 1], as the official loader
    x = u8.permute(*range(u8.dim() - 3), -1, -3, -2).float()
    return x / 127.5 - 1.0


def matrices(poses):
    """(..., 3) absolute (x, y, yaw rad) -> (..., 4, 4) ego-to-world matrices (the official rot_matrix)."""
    c, s = torch.cos(poses[..., 2]), torch.sin(poses[..., 2])
    m = torch.zeros(*poses.shape[:-1], 4, 4, dtype=poses.dtype, device=poses.device)
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1] = c, -s, s, c
    m[..., 2, 2] = m[..., 3, 3] = 1
    m[..., 0, 3], m[..., 1, 3] = poses[..., 0], poses[..., 1]
    return m


def lr_at(step, progress, peak, warmup):
    """Linear warm-up over `warmup` steps, then a cosine over the planned wall time: `progress` is
    the training seconds so far over --schedule-seconds, so that a run chunked into device calls of
    fixed length ends its decay on time whatever its speed."""
    if step < warmup:
        return peak * (step + 1) / warmup
    return peak * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress))))


class Curve:
    """Loss curve written as JSON lines beside the checkpoints (docs/training.md plots it)."""

    def __init__(self, path):
        self.path = path

    def add(self, **row):
        with open(self.path, "a") as f:
            f.write(json.dumps(row) + "\n")


def save_atomic(obj, path):
    tmp = path + ".tmp"
    torch.save(obj, tmp)
    os.replace(tmp, path)


def checkpoint(path, module, opt, step, seconds):
    """Weights, optimiser state, steps and training seconds so far (what --seconds chunks resume)."""
    save_atomic({"model": module.state_dict(), "opt": opt.state_dict(), "step": step, "seconds": seconds}, path)


def resume(path, module, opt, device, what):
    """(step, training seconds) of the checkpoint at `path`, loaded into module and opt; (0, 0) if none."""
    if not os.path.exists(path):
        return 0, 0.0
    state = torch.load(path, map_location=device)
    module.load_state_dict(state["model"])
    opt.load_state_dict(state["opt"])
    log(f"resumed {what} at step {state['step']}")
    return state["step"], state.get("seconds", 0.0)


# ---------------------------------------------------------------------------------------- DC-AE

def latent_stats_penalty(z):
    mean = z.float().mean(dim=(0, 2, 3))
    std = z.float().std(dim=(0, 2, 3))
    return (mean ** 2).mean() + ((std - 1) ** 2).mean()


def train_dcae(a):
    off = official.load(a.official, a.device, triton_rmsnorm=False)
    configs = model_configs(a.model)
    torch.manual_seed(a.seed)
    ae = official.build_dcae(off, configs, a.device)
    log(f"DC-AE: {sum(p.numel() for p in ae.parameters()) / 1e6:.2f} M parameters")
    frames, _ = load_clips(a.data, a.device, a.limit_clips)
    n_img = frames.shape[0] * frames.shape[1]
    flat = frames.reshape(n_img, *frames.shape[2:])
    params = [p for n, p in ae.named_parameters() if not n.startswith(("causal_time_block", "space_block"))]
    opt = torch.optim.AdamW(params, lr=a.lr, betas=(0.9, 0.95), weight_decay=0.01)
    ckpt = os.path.join(a.work, "dcae.pt")
    step, done = resume(ckpt, ae, opt, a.device, "the DC-AE")
    curve = Curve(os.path.join(a.work, "dcae_loss.jsonl"))
    gen = torch.Generator(device=a.device).manual_seed(a.seed + step)
    t0 = time.time()
    ae.train()
    autocast = torch.autocast(device_type="cuda" if a.device == "cuda" else "cpu", dtype=torch.bfloat16)
    while step < a.steps and time.time() - t0 < a.seconds:
        for g in opt.param_groups:
            g["lr"] = lr_at(step, (done + time.time() - t0) / a.schedule_seconds, a.lr, 200)
        idx = torch.randint(0, n_img, (a.batch,), device=a.device, generator=gen)
        x = to_model_range(flat[idx])
        with autocast:
            z = ae.encoder(x)
            sigma = torch.rand(z.shape[0], 1, 1, 1, device=z.device, generator=gen) * a.latent_noise
            zn = z + sigma * torch.randn(z.shape, device=z.device, generator=gen)
            y = ae.decoder(zn)
        y = y.float()
        l1 = (y - x).abs().mean()
        mse = ((y - x) ** 2).mean()
        reg = latent_stats_penalty(z)
        loss = l1 + mse + a.latent_weight * reg
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        step += 1
        if step % 50 == 0 or step == 1:
            psnr = 10 * math.log10(4.0 / max(mse.item(), 1e-10))  # [-1, 1] range: peak-to-peak 2
            curve.add(step=step, seconds=round(time.time() - t0, 2), l1=l1.item(), mse=mse.item(),
                      latent_penalty=reg.item(), psnr=psnr, latent_std=z.float().std().item())
            log(f"dcae step {step} l1 {l1.item():.4f} psnr {psnr:.2f} latent std {z.float().std().item():.3f}")
        if step % 500 == 0:
            checkpoint(ckpt, ae, opt, step, done + time.time() - t0)
    checkpoint(ckpt, ae, opt, step, done + time.time() - t0)
    log(f"DC-AE: {step} steps, {time.time() - t0:.0f} s")


@torch.no_grad()
def encode_all(a):
    """Encodes every frame once with the trained DC-AE (eval mode): the world model's data."""
    off = official.load(a.official, a.device, triton_rmsnorm=False)
    configs = model_configs(a.model)
    ae = official.build_dcae(off, configs, a.device).eval()
    ckpt = os.path.join(a.work, "dcae.pt")
    ae.load_state_dict(torch.load(ckpt, map_location=a.device)["model"] if os.path.exists(ckpt) else
                       exported_state(a.init, "weights_dcae", ""))
    sets = [(a.data, True)] + ([(a.explore_data, False)] if a.explore_data else [])
    lat, poses, natural = [], [], []
    for folder, is_natural in sets:
        frames, p = load_clips(folder, a.device, a.limit_clips)
        lat.append(encode_frames(ae, frames))
        poses.append(p.cpu())
        natural.append(torch.full((frames.shape[0],), is_natural))
        del frames
    t, tp = min(x.shape[1] for x in lat), min(x.shape[1] for x in poses)
    lat = torch.cat([x[:, :t] for x in lat])
    log(f"latents {tuple(lat.shape)}: mean {lat.mean().item():.3f} std {lat.std().item():.3f}")
    torch.save({"latents": lat, "poses": torch.cat([x[:, :tp] for x in poses]), "natural": torch.cat(natural)},
               os.path.join(a.work, "latents.pt"))


def encode_frames(ae, frames):
    """(N, T, H, W, 3) uint8 -> (N, T, h*w, 32) latents on the CPU, patchified with patch 1 (row-major)."""
    n, t = frames.shape[:2]
    flat = frames.reshape(n * t, *frames.shape[2:])
    out = []
    for i in range(0, flat.shape[0], 128):
        z = ae.encode(to_model_range(flat[i:i + 128])).float()  # (b, 32, h, w)
        out.append(z.flatten(2).transpose(1, 2).cpu())
    return torch.cat(out).reshape(n, t, *out[0].shape[1:])


# ---------------------------------------------------------------------------------------- world model

def exported_state(folder, name, prefix):
    """A state_dict from an exported model folder (--init), float32, `prefix` stripped."""
    from safetensors.torch import load_file
    if not folder:
        raise SystemExit("no checkpoint in --work and no --init folder to start from")
    t = load_file(os.path.join(folder, name + ".safetensors"))
    return {k[len(prefix):]: (v.float() if v.is_floating_point() else v) for k, v in t.items() if k.startswith(prefix)}


def trajectory_loss(wm, latents_total, rot):
    """The TrajDiT half of the official model_forward, with the MST frozen (--trajectory-only): the
    same relative poses, tokens, MST features and normalised targets, and TrajDiT.training_losses."""
    mm = sys.modules["models.model"]  # the official module's own helpers (matrix get_rel_pose/_traj)
    F = wm.condition_frames
    with torch.no_grad():
        with torch.autocast(device_type="cuda", enabled=False):
            rel_pose, rel_yaw = mm.get_rel_pose(rot[:, :F + 1])
            traj_poses, traj_yaws = mm.get_rel_traj(rot, F, wm.traj_len)
        pose_idx = mm.poses_to_indices(rel_pose, wm.pose_x_vocab_size, wm.pose_y_vocab_size)
        yaw_idx = mm.yaws_to_indices(rel_yaw, wm.yaw_vocab_size)
        stt = wm.model(latents_total, pose_idx, yaw_idx, drop_feature=wm.args.drop_feature)["logits"]
        targets = wm.normalize_traj(torch.cat([traj_poses, traj_yaws], dim=-1).reshape(-1, wm.traj_len, 3))
    t = torch.rand((targets.shape[0], 1, 1), device=targets.device)
    return wm.traj_dit.training_losses(traj=targets, traj_ids=wm.traj_ids, cond=stt, cond_ids=wm.cond_ids, t=t)["loss"]


def world_batch(lat, poses, F, fi, traj_len, batch, gen, clips):
    """Windows of F + fi latents and F + traj_len + fi - 1 poses, as the official loop slices them,
    from the clips listed in `clips`."""
    t = lat.shape[1]
    n_frames, n_poses = F + fi, F + traj_len + fi - 1
    last_start = min(t - n_frames, poses.shape[1] - n_poses)
    clip = clips[torch.randint(0, clips.numel(), (batch,), device=lat.device, generator=gen)]
    start = torch.randint(0, last_start + 1, (batch,), device=lat.device, generator=gen)
    fr = start[:, None] + torch.arange(n_frames, device=lat.device)
    po = start[:, None] + torch.arange(n_poses, device=lat.device)
    return lat[clip[:, None], fr], matrices(poses[clip[:, None], po]).float()


class _cpu_float32:
    """CPU runs (smoke tests) in float32: the official model_forward casts the trajectory targets to
    bfloat16 for the GPU's autocast, which the CPU's layer norm does not accept; cast them back."""

    def __init__(self, wm):
        losses = wm.traj_dit.training_losses
        wm.traj_dit.training_losses = lambda traj, **kw: losses(traj=traj.float(), **kw)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def train_world(a):
    off = official.load(a.official, a.device, triton_rmsnorm=False)
    configs = model_configs(a.model)
    args = official.world_args(configs)
    torch.manual_seed(a.seed)
    wm = official.build_world(off, configs, a.device, batch_size=a.batch)
    counts = {k: sum(p.numel() for p in getattr(wm, k).parameters()) / 1e6 for k in ("model", "dit", "traj_dit")}
    log("world model: MST {model:.2f} M, VisDiT {dit:.2f} M, TrajDiT {traj_dit:.2f} M parameters".format(**counts))
    data = torch.load(os.path.join(a.work, "latents.pt"))
    lat, poses = data["latents"].to(a.device), data["poses"].to(a.device)
    natural = data.get("natural", torch.ones(lat.shape[0], dtype=torch.bool)).to(a.device)
    natural_clips, exploring_clips = natural.nonzero()[:, 0], (~natural).nonzero()[:, 0]
    log(f"{natural_clips.numel()} natural clips, {exploring_clips.numel()} of the exploring driver")
    ckpt = os.path.join(a.work, "world.pt")
    if not os.path.exists(ckpt) and a.init:
        for sub in ("model", "dit", "traj_dit"):
            getattr(wm, sub).load_state_dict(exported_state(a.init, "weights_world", f"module.{sub}."))
        log(f"started from the exported model in {a.init}")
    trained = wm.traj_dit.parameters() if a.trajectory_only else wm.parameters()
    if a.trajectory_only:  # the MST and the VisDiT stay exactly as they are
        for sub in (wm.model, wm.dit):
            sub.eval().requires_grad_(False)
    opt = torch.optim.AdamW(trained, lr=a.lr, betas=(0.9, 0.95), weight_decay=0.01)
    step, done = resume(ckpt, wm, opt, a.device, "the world model")
    curve = Curve(os.path.join(a.work, "world_loss.jsonl"))
    gen = torch.Generator(device=a.device).manual_seed(a.seed + 7919 * step + 1)
    F, fi, traj_len = args.condition_frames, args.forward_iter, args.traj_len
    autocast = torch.autocast(device_type="cuda", dtype=torch.bfloat16) if a.device == "cuda" else _cpu_float32(wm)
    t0 = time.time()
    last_save = t0
    while step < a.steps and time.time() - t0 < a.seconds:
        lr = lr_at(step, (done + time.time() - t0) / a.schedule_seconds, a.lr, 300)
        for g in opt.param_groups:
            g["lr"] = lr
        # Batches of the exploring driver (a share explore_share of the steps, spread evenly) teach the
        # VisDiT to follow the action; their futures hold random impulses no planner should imitate, so
        # they train no trajectory.
        exploring = exploring_clips.numel() > 0 and int((step + 1) * a.explore_share) > int(step * a.explore_share)
        latents, rot = world_batch(lat, poses, F, fi, traj_len, a.batch, gen, exploring_clips if exploring else natural_clips)
        latents_cond = latents[:, :F]
        rel_pose_cond = rel_yaw_cond = None
        passes = fi if step % args.multifw_perstep == 0 and not a.trajectory_only else 1
        if a.trajectory_only:
            wm.traj_dit.train()
            with autocast:
                loss = trajectory_loss(wm, latents[:, :F + 1], rot[:, :F + traj_len])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(wm.traj_dit.parameters(), 1.0)
            opt.step()
            out = {"loss_diff": torch.zeros(()), "loss_yaw_pose": loss.detach()}
            passes = 0
        else:
            wm.train()
        for j in range(passes):  # the official chain-of-forward (scripts/train_deepspeed.py)
            rot_cond = rot[:, j:j + F + traj_len]
            latents_gt = latents[:, j + F:j + F + 1]
            with autocast:
                out = wm(latents_cond, rot_cond, latents_gt, rel_pose_cond=rel_pose_cond, rel_yaw_cond=rel_yaw_cond)
            loss = out["loss_diff"] if exploring else out["loss_all"]
            if not math.isfinite(loss.item()):
                raise SystemExit(f"loss is {loss.item()} at step {step}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(wm.parameters(), 1.0)
            opt.step()
            if j < passes - 1:
                pred = out["predict"].detach().float()
                traj = out["predict_traj"].detach().float()
                latents_cond = pred.reshape(a.batch, F, *pred.shape[1:])
                rel = traj.reshape(a.batch, F, *traj.shape[1:])[:, :, 0, :]
                rel = wm.denormalize_traj(rel.clone())  # the official loop feeds normalised values back;
                # its pose tokenizer expects metres and degrees, so we denormalise first (docs/training.md)
                rel_pose_cond, rel_yaw_cond = rel[..., 0:2], rel[..., 2:3]
        step += 1
        if step % 25 == 0 or step == 1:
            curve.add(step=step, seconds=round(time.time() - t0, 2), lr=lr, loss=loss.item(),
                      loss_diff=out["loss_diff"].item(), loss_traj=out["loss_yaw_pose"].item(), passes=passes,
                      exploring=bool(exploring))
        if step % 100 == 0:
            log(f"world step {step} loss {loss.item():.4f} (video {out['loss_diff'].item():.4f}, "
                f"trajectory {out['loss_yaw_pose'].item():.4f}) lr {lr:.2e}")
        if time.time() - last_save > a.save_every:
            checkpoint(ckpt, wm, opt, step, done + time.time() - t0)
            export(a, configs, wm=wm)
            last_save = time.time()
    checkpoint(ckpt, wm, opt, step, done + time.time() - t0)
    export(a, configs, wm=wm)
    log(f"world model: {step} steps, {time.time() - t0:.0f} s")


# ---------------------------------------------------------------------------------------- export

def bf16_state(module, prefix=""):
    out = {}
    for k, v in module.state_dict().items():
        out[prefix + k] = v.detach().to(torch.bfloat16).cpu() if v.is_floating_point() else v.detach().cpu()
    return out


def export(a, configs, wm=None):
    """bf16 weights + configs.json into --export (default WORK/small): what epona loads."""
    from safetensors.torch import save_file
    dest = a.export or os.path.join(a.work, "small")
    os.makedirs(dest, exist_ok=True)
    if wm is not None:
        world = {}
        for sub in ("model", "dit", "traj_dit"):
            world.update(bf16_state(getattr(wm, sub), f"module.{sub}."))
        save_file(world, os.path.join(dest, "weights_world.safetensors.tmp"), metadata={"producer": "epona training/train.py", "set": configs["set"]})
        os.replace(os.path.join(dest, "weights_world.safetensors.tmp"), os.path.join(dest, "weights_world.safetensors"))
    dcae_ckpt = os.path.join(a.work, "dcae.pt")
    if os.path.exists(dcae_ckpt):
        off_state = torch.load(dcae_ckpt, map_location="cpu")["model"]
        ae = {k: (v.to(torch.bfloat16) if v.is_floating_point() else v) for k, v in off_state.items()}
        save_file(ae, os.path.join(dest, "weights_dcae.safetensors.tmp"), metadata={"producer": "epona training/train.py", "set": configs["set"]})
        os.replace(os.path.join(dest, "weights_dcae.safetensors.tmp"), os.path.join(dest, "weights_dcae.safetensors"))
    with open(os.path.join(dest, "configs.json"), "w") as f:
        json.dump(configs, f, indent=1)


def run_export(a):
    off = official.load(a.official, a.device, triton_rmsnorm=False)
    configs = model_configs(a.model)
    wm = None
    ckpt = os.path.join(a.work, "world.pt")
    if os.path.exists(ckpt):
        wm = official.build_world(off, configs, a.device)
        wm.load_state_dict(torch.load(ckpt, map_location=a.device)["model"])
    export(a, configs, wm=wm)


@torch.no_grad()
def preview(a):
    """A quick look, PyTorch side: DC-AE reconstructions and one-step predictions of the world model
    (official step_eval under the true next action) against the true next frame, with PSNR beside
    "repeat the last frame", on the first clips of --data. Writes WORK/preview.png and preview.json."""
    from PIL import Image
    off = official.load(a.official, a.device, triton_rmsnorm=False)
    configs = model_configs(a.model)
    args = official.world_args(configs)
    ae = official.build_dcae(off, configs, a.device).eval()
    ckpt = os.path.join(a.work, "dcae.pt")
    ae.load_state_dict(torch.load(ckpt, map_location=a.device)["model"] if os.path.exists(ckpt) else
                       exported_state(a.init, "weights_dcae", ""))
    wm = official.build_world(off, configs, a.device).eval()
    wm.load_state_dict(torch.load(os.path.join(a.work, "world.pt"), map_location=a.device)["model"])
    args.num_sampling_steps = a.preview_steps
    wm.args.num_sampling_steps = a.preview_steps
    frames, poses = load_clips(a.data, a.device, a.limit_clips or 8)
    F = args.condition_frames
    h, w = configs["derived"]["latent_h"], configs["derived"]["latent_w"]
    rows, stats = [], {"psnr_model": [], "psnr_repeat": [], "psnr_autoencoder": []}
    psnr = lambda x, y: 10 * math.log10(4.0 / max(((x - y) ** 2).mean().item(), 1e-10))  # noqa: E731
    for c in range(frames.shape[0]):
        x = to_model_range(frames[c, :F + 1])  # (F+1, 3, H, W)
        z = ae.encode(x).float()
        lat = z.flatten(2).transpose(1, 2)[None, :F]  # (1, F, L, 32)
        rel_pose, rel_yaw = off.get_rel_pose(poses[c:c + 1, :F + 1].float().clone())
        devnull = open(os.devnull, "w")
        stdout, sys.stdout = sys.stdout, devnull
        try:
            with (torch.autocast(device_type="cuda", dtype=torch.bfloat16) if a.device == "cuda" else contextlib.nullcontext()):
                _, pred = wm.step_eval(lat, rel_pose, torch.rad2deg(rel_yaw), self_pred_traj=False)
        finally:
            sys.stdout = stdout
        img = ae.decode(pred.float().permute(0, 3, 1, 2), is_video=False).clamp(-1, 1)[0]
        rec = ae.decode(z[F:F + 1], is_video=False).clamp(-1, 1)[0]
        stats["psnr_model"].append(psnr(img, x[F]))
        stats["psnr_repeat"].append(psnr(x[F - 1], x[F]))
        stats["psnr_autoencoder"].append(psnr(rec, x[F]))
        rows.append(torch.cat([x[F - 1], x[F], rec, img], dim=2))
    summary = {k: sum(v) / len(v) for k, v in stats.items()}
    log("preview:", json.dumps(summary))
    grid = torch.cat(rows, dim=1)
    Image.fromarray(((grid.permute(1, 2, 0) + 1) * 127.5).round().clamp(0, 255).byte().cpu().numpy()).save(
        os.path.join(a.work, "preview.png"))
    with open(os.path.join(a.work, "preview.json"), "w") as f:
        json.dump({"summary": summary, **stats}, f, indent=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage", choices=["dcae", "encode", "world", "export", "preview"])
    ap.add_argument("--official", required=True, help="checkout of Kevin-thu/Epona")
    ap.add_argument("--data", help="folder of `epona synth --format npy` clips")
    ap.add_argument("--explore-data", default="", help="encode: a second folder, of `epona synth --explore` clips")
    ap.add_argument("--explore-share", type=float, default=0.5,
                    help="world: the share of steps whose batch comes from the exploring driver's clips (if encoded)")
    ap.add_argument("--work", required=True, help="checkpoints, logs, latent cache")
    ap.add_argument("--model", default=os.path.join(HERE, "small_epona.json"))
    ap.add_argument("--export", default="", help="export folder (default WORK/small)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=10**9, help="stop after this many steps")
    ap.add_argument("--seconds", type=float, default=1e9, help="stop after this wall time (resumable)")
    ap.add_argument("--schedule-seconds", type=float, default=600.0,
                    help="planned training time of the stage over all its runs: the learning rate's cosine ends there")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit-clips", type=int, default=0)
    ap.add_argument("--latent-noise", type=float, default=0.2, help="DC-AE: max std of the decoder's latent noise")
    ap.add_argument("--latent-weight", type=float, default=0.1, help="DC-AE: weight of the latent-statistics penalty")
    ap.add_argument("--save-every", type=float, default=60.0, help="seconds between checkpoints")
    ap.add_argument("--preview-steps", type=int, default=30, help="preview: sampling steps")
    ap.add_argument("--init", default="", help="an exported model folder to start from where --work has no checkpoint")
    ap.add_argument("--trajectory-only", action="store_true",
                    help="world: train the TrajDiT alone on the trajectory loss, the MST and VisDiT frozen")
    a = ap.parse_args()
    os.makedirs(a.work, exist_ok=True)
    if a.device == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
        torch.backends.cudnn.benchmark = True
    {"dcae": train_dcae, "encode": encode_all, "world": train_world, "export": run_export,
     "preview": preview}[a.stage](a)


if __name__ == "__main__":
    main()
