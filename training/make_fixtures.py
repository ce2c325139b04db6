#!/usr/bin/env python3
"""Golden vectors (the format of tests/data/golden) for a model given by its weights, computed by the
OFFICIAL Epona code (imported from a checkout through training/official.py; none of it is copied).

    /usr/bin/python3 training/make_fixtures.py --official /work/epona-official --model DIR --out OUTDIR \
        [--inputs-from GOLDEN_DIR] [--clip CLIPDIR] [--seed N] [--device cpu|cuda] [--copy-weights]

DIR holds configs.json (golden layout) + weights_world.safetensors + weights_dcae.safetensors (any
float dtype: bfloat16 weights are upcast to float32, so the fixtures are the float32 computation
on exactly the stored values). OUTDIR receives cases.safetensors, manifest.json and configs.json
(the weights only with --copy-weights; otherwise link them in).

Every tensor of the public manifest is computed, with the meanings of tests/data/golden/README.md:
each stage from stored tensors (a stage that consumes an earlier output consumes its stored
float32 value). Inputs: a seeded generator (realistic pose/yaw ranges, out-of-range tokenizer
values), or with --clip the DC-AE latents and motions of a real clip (frames/*.png, poses.csv,
optionally future_poses.csv and future/*.png), or with --inputs-from the input tensors of another
set (self-check: regenerate a set and compare with training/compare_cases.py).

The manifest's tolerance sections are measured, not copied: `tolerance.repeat_after_reload` (a
second build of both models read back through the official loaders, every output recomputed),
`tolerance.gpu_default_sdpa` (cuda only), and `tolerance_official_bf16_recipe` (the world model
under bf16 autocast with float32 weights, the DC-AE in float32 with PyTorch's default TF32 flags,
and for reference the DC-AE under bf16 autocast), each per output tensor against the float32
values. On the CPU, autocast is the CPU's (the official recipe is CUDA's): the manifest says so.
"""
import argparse
import contextlib
import glob
import io
import json
import math
import os
import shutil
import sys
import tempfile
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import official  # noqa: E402

TEMPLATE_DIR = os.path.join(official.ROOT, "tests", "data", "golden")
ROLLOUT_STEPS = 2

INPUTS = ["emb.fourier.coords", "temb.t", "tok.rel_pose", "tok.rel_yaw", "mst.latents", "mst.rel_pose",
          "mst.rel_yaw", "traj.x", "traj.t", "vis.x", "vis.t", "traj.sample.noise", "vis.sample.noise",
          "rollout.noise_traj", "rollout.noise_img", "dcae.decode.latent_in", "dcae.clip.latent_in"]
DECODE_STAGES = (5, 4)      # dcae.decode.stage{i}_out
ENCODE_STAGES = (3, 4, 5)   # dcae.encode.stage{i}_out


def log(*a):
    print(time.strftime("%H:%M:%S"), *a, flush=True)


# ---------------------------------------------------------------------------------------- setup

def deterministic(device):
    torch.backends.cudnn.deterministic = True
    torch.backends.cudnn.benchmark = False
    set_tf32(False)
    if device == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        set_sdpa_math(True)


def set_tf32(on):
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.backends.cudnn.allow_tf32 = on


def set_sdpa_math(only_math):
    for name in ("enable_flash_sdp", "enable_mem_efficient_sdp", "enable_cudnn_sdp"):
        fn = getattr(torch.backends.cuda, name, None)
        if fn is not None:
            fn(not only_math)
    if hasattr(torch.backends.cuda, "enable_math_sdp"):
        torch.backends.cuda.enable_math_sdp(True)


def modern_linspace_for_old_torch(off_checkout):
    """torch < 2 (Debian's python3-torch 1.13) computes float32 linspace differently from current
    PyTorch (which fills the first half as start + step*i, the second as end - step*(steps-1-i)),
    so get_schedule(100, ...) differs in a few ulps from the official grid on current PyTorch
    (and from the C++ port, which the parity test holds bit-exact). Give the official sampling
    module current PyTorch's linspace; nothing else uses it."""
    if int(torch.__version__.split(".")[0]) >= 2:
        return
    from models.modules import sampling

    def linspace(start, end, steps, dtype=None, device=None, **kw):
        if dtype not in (None, torch.float32) or kw:
            return torch.linspace(start, end, steps, dtype=dtype, device=device, **kw)
        n = steps - 1
        f32 = torch.float32
        step = (torch.tensor(float(end), dtype=f32) - torch.tensor(float(start), dtype=f32)) / torch.tensor(float(max(n, 1)), dtype=f32)
        i = torch.arange(steps)
        first = (step.double() * i.double() + float(start)).float()  # one rounding, as the FMA
        second = torch.tensor(float(end), dtype=f32) - step * (n - i).float()
        return torch.where(i < steps // 2, first, second).to(device or "cpu")

    class _Torch:
        def __getattr__(self, name):
            return linspace if name == "linspace" else getattr(torch, name)

    sampling.torch = _Torch()


def load_safetensors(path):
    from safetensors.torch import load_file
    return load_file(path)


def file_dtypes(path):
    """{name: (shape, dtype name)} from a safetensors header (the stored dtype, before any upcast)."""
    import struct
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(n))
    names = {"F32": "float32", "BF16": "bfloat16", "F16": "float16", "I64": "int64", "F64": "float64"}
    return {k: [v["shape"], names[v["dtype"]]] for k, v in header.items() if k != "__metadata__"}


def upcast(sd):
    return {k: (v.float() if v.is_floating_point() else v) for k, v in sd.items()}


@contextlib.contextmanager
def quiet():
    """The official constructors and step_eval print; keep the log readable."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        yield


def build_models(off, configs, model_dir, device, init_seed):
    """Both official modules, weights read the way the official loaders read them:
    TrainTransformersDiT(load_path=...) from a torch.save'd {"model_state_dict": ...} (the
    `module.model.` / `module.dit.` / `module.traj_dit.` keys), DCAE.load_state_dict(state_dict)
    as DCAE.load_model does with a .safetensors file. Weights are upcast to float32 first."""
    world_sd = upcast(load_safetensors(os.path.join(model_dir, "weights_world.safetensors")))
    dcae_sd = upcast(load_safetensors(os.path.join(model_dir, "weights_dcae.safetensors")))
    torch.manual_seed(init_seed)  # the random init is overwritten; a different one per build
    args = official.world_args(configs)
    args.batch_size = 1
    with tempfile.TemporaryDirectory() as tmp, quiet():
        pkl = os.path.join(tmp, "world.pkl")
        torch.save({"model_state_dict": world_sd}, pkl)
        wm = off.TrainTransformersDiT(args, local_rank=0, load_path=pkl, condition_frames=args.condition_frames)
    wm = wm.to(device).eval()
    used = {"module.model." + k for k in wm.model.state_dict()} | {"module.dit." + k for k in wm.dit.state_dict()} | \
        {"module.traj_dit." + k for k in wm.traj_dit.state_dict()}
    extra = sorted(set(world_sd) - used)
    if extra:
        raise SystemExit(f"weights_world.safetensors: {len(extra)} keys the official model does not have, e.g. {extra[:3]}")
    with quiet():
        ae = official.build_dcae(off, configs, device)
    ae.load_state_dict({k: v.to(device) for k, v in dcae_sd.items()})  # strict, as DCAE.load_model
    ae = ae.eval()
    return wm, ae


# ---------------------------------------------------------------------------------------- inputs

def sizes(configs):
    w = configs["world_model_config"]
    d = configs["derived"]
    dc = configs["dcae"]
    return dict(B=1, F=w["condition_frames"], h=d["latent_h"], w=d["latent_w"], L=d["img_tokens"],
                T=d["total_tokens"], C=w["n_embd"], traj_len=w["traj_len"], N=w["num_sampling_steps"],
                S=ROLLOUT_STEPS, vae=w["vae_embed_dim"], dh=dc["latent_size"][0], dw=dc["latent_size"][1],
                Tc=dc["config"]["condition_frames"], image=tuple(dc["image_size"]),
                world_image=tuple(w["image_size"]), n_mst=configs["mst"]["n_layer_causal_time_space"],
                widths=list(dc["config"]["decoder"]["width_list"]), enc_widths=list(dc["config"]["encoder"]["width_list"]))


def random_inputs(s, seed):
    g = torch.Generator().manual_seed(seed)

    def u(shape, lo, hi):
        return lo + (hi - lo) * torch.rand(shape, generator=g)

    def n(*shape):
        return torch.randn(*shape, generator=g)

    B, F = s["B"], s["F"]
    x = {}
    # Fourier coordinates: normalised indices in [0, 1] for F+1 frames.
    x["emb.fourier.coords"] = u((B, F + 1, 3), 0.0, 1.0)
    x["temb.t"] = torch.tensor([0.0, 0.25, float(u((1,), 0.0, 1.0)), 1.0])
    # Tokenizer: the range edges and out-of-range values (clipping), then realistic random motions.
    edge_pose = [[-1.0, -0.9], [0.0, -0.5], [0.03, -0.49], [3.3, 0.0], [7.99, 0.2], [8.0, 0.5], [9.5, 0.51],
                 [100.0, 2.0]]
    edge_yaw = [-20.0, -8.0, -7.99, 0.0, 0.01, 7.98, 8.0, 30.0]
    extra = 4
    rp = torch.cat([torch.tensor(edge_pose), torch.stack([u((extra,), 0.0, 8.0), u((extra,), -0.5, 0.5)], 1)])
    ry = torch.cat([torch.tensor(edge_yaw), u((extra,), -8.0, 8.0)])
    x["tok.rel_pose"] = rp.reshape(1, -1, 2).repeat(B, 1, 1)
    x["tok.rel_yaw"] = ry.reshape(1, -1, 1).repeat(B, 1, 1)
    x["mst.latents"] = n(B, F, s["L"], s["vae"])
    # Motion into each frame of the window (+ the target): 0.5..7.5 m forward, +-0.4 m, +-6 deg.
    pose = torch.stack([u((B, F + 1), 0.5, 7.5), u((B, F + 1), -0.4, 0.4)], -1)
    yaw = u((B, F + 1, 1), -6.0, 6.0)
    pose[:, 0] = 0.0  # the first window frame has no motion (official get_rel_pose)
    yaw[:, 0] = 0.0
    x["mst.rel_pose"], x["mst.rel_yaw"] = pose, yaw
    x["traj.x"] = n(B, s["traj_len"], 3)
    x["traj.t"] = u((B,), 0.05, 0.95)
    x["vis.x"] = n(B, s["L"], s["vae"])
    x["vis.t"] = u((B,), 0.05, 0.95)
    x["traj.sample.noise"] = n(B, s["traj_len"], 3)
    x["vis.sample.noise"] = n(B, s["L"], s["vae"])
    x["rollout.noise_traj"] = n(s["S"], B, s["traj_len"], 3)
    x["rollout.noise_img"] = n(s["S"], B, s["L"], s["vae"])
    x["dcae.decode.latent_in"] = n(1, s["vae"], s["dh"], s["dw"])
    x["dcae.clip.latent_in"] = n(s["Tc"], s["vae"], s["dh"], s["dw"])
    return x


def read_motions(path):
    """x,y,yaw rows (metres, metres, degrees); '#' comments and a header line allowed."""
    rows = []
    with open(path) as f:
        for line in f:
            line = line.split("#", 1)[0].strip().lstrip("\ufeff")
            if not line:
                continue
            parts = [p for p in line.replace(",", " ").split()]
            try:
                rows.append([float(p) for p in parts[:3]])
            except ValueError:
                continue  # header
    return torch.tensor(rows, dtype=torch.float32).reshape(-1, 3)


def read_frames(paths, size):
    import numpy as np
    from PIL import Image
    out = []
    for p in paths:
        im = Image.open(p).convert("RGB")
        if im.size != (size[1], size[0]):
            im = im.resize((size[1], size[0]), Image.BILINEAR)
        out.append(torch.from_numpy(np.asarray(im).copy()))
    u8 = torch.stack(out)  # (n, H, W, 3)
    return u8.permute(0, 3, 1, 2).float() / 127.5 - 1.0  # the official loader's [-1, 1]


def trajectory_from_motions(m):
    """Motions into successive frames (x, y, yaw deg; each in the previous frame's ego frame) ->
    poses (x, y, yaw deg) in the ego frame of the frame before the first motion."""
    x = y = th = 0.0
    out = []
    for dx, dy, dyaw in m.tolist():
        c, s_ = math.cos(th), math.sin(th)
        x, y = x + c * dx - s_ * dy, y + s_ * dx + c * dy
        th += math.radians(dyaw)
        out.append([x, y, math.degrees(th)])
    return torch.tensor(out, dtype=torch.float32)


@torch.no_grad()
def clip_inputs(x, s, clip_dir, ae, wm, device):
    """Replaces the latent and motion inputs by those of a real clip."""
    frames = sorted(glob.glob(os.path.join(clip_dir, "frames", "*.png")))
    motions = read_motions(os.path.join(clip_dir, "poses.csv"))
    F, Tc = s["F"], s["Tc"]
    if len(frames) < max(F, Tc):
        raise SystemExit(f"--clip {clip_dir}: {len(frames)} frames in frames/, need {max(F, Tc)}")
    if motions.shape[0] != len(frames):
        raise SystemExit(f"--clip {clip_dir}: poses.csv holds {motions.shape[0]} rows for {len(frames)} frames")
    future_path = os.path.join(clip_dir, "future_poses.csv")
    future = read_motions(future_path) if os.path.exists(future_path) else None

    def encode(paths, size):
        img = read_frames(paths, size).to(device)
        return torch.cat([ae.encode(img[i:i + 1]).float() for i in range(img.shape[0])])  # (n, 32, h, w)

    z = encode(frames[-F:], s["world_image"])  # the world model's frames
    x["mst.latents"] = z.flatten(2).transpose(1, 2).unsqueeze(0).cpu()  # (1, F, L, 32), patch 1 row-major
    window = motions[-F:]
    target = future[0:1] if future is not None and future.shape[0] else motions[-1:]
    win = torch.cat([window, target])
    x["mst.rel_pose"] = win[None, :, 0:2].clone()
    x["mst.rel_yaw"] = win[None, :, 2:3].clone()
    # DiT states on the rectified-flow path x_t = t*data + (1-t)*noise (official training_losses).
    future_frames = sorted(glob.glob(os.path.join(clip_dir, "future", "*.png")))
    data = encode(future_frames[:1], s["world_image"]) if future_frames else z[-1:]
    data = data.flatten(2).transpose(1, 2).cpu()
    t = float(x["vis.t"][0])
    x["vis.x"] = t * data + (1 - t) * x["vis.sample.noise"]
    if future is not None and future.shape[0] >= s["traj_len"]:
        traj = trajectory_from_motions(future[:s["traj_len"]])[None]
        traj = wm.normalize_traj(traj.clone())
        t = float(x["traj.t"][0])
        x["traj.x"] = t * traj + (1 - t) * x["traj.sample.noise"]
    zd = encode(frames[-Tc:], s["image"])  # the DC-AE cases' frame size
    x["dcae.decode.latent_in"] = zd[-1:].cpu()
    x["dcae.clip.latent_in"] = zd.cpu()
    return x, {"clip": os.path.abspath(clip_dir), "frames": [os.path.basename(p) for p in frames[-max(F, Tc):]],
               "target_motion": "future_poses.csv row 0" if future is not None else "last poses.csv row repeated",
               "vis.x": "t*latent(" + ("future frame 0" if future_frames else "last frame") + ") + (1-t)*vis.sample.noise",
               "traj.x": ("t*normalised future trajectory + (1-t)*traj.sample.noise"
                          if future is not None and future.shape[0] >= s["traj_len"] else "random normal")}


# ---------------------------------------------------------------------------------------- outputs

@torch.no_grad()
def compute(off, wm, ae, x, s, device, world_ctx=contextlib.nullcontext, dcae_ctx=contextlib.nullcontext):
    """Every output tensor from the inputs `x` (CPU float32 tensors); returns CPU float32 tensors."""
    from utils.embeddings import get_fourier_embeds_from_coordinates
    from models.modules.dit_modules.layers import timestep_embedding
    import models.model as model_module
    from einops import rearrange

    dev = {k: v.to(device) for k, v in x.items()}
    out = {}

    def put(name, t):
        out[name] = t.detach().float().cpu().contiguous()

    B, F, h, w = s["B"], s["F"], s["h"], s["w"]
    with world_ctx():
        put("emb.fourier.out", get_fourier_embeds_from_coordinates(512, dev["emb.fourier.coords"]))
        put("temb.out", timestep_embedding(dev["temb.t"], 256))
        put("tok.pose_idx", off.poses_to_indices(dev["tok.rel_pose"], wm.pose_x_vocab_size, wm.pose_y_vocab_size))
        put("tok.yaw_idx", off.yaws_to_indices(dev["tok.rel_yaw"], wm.yaw_vocab_size))
        pose_idx = off.poses_to_indices(dev["mst.rel_pose"], wm.pose_x_vocab_size, wm.pose_y_vocab_size)
        yaw_idx = off.yaws_to_indices(dev["mst.rel_yaw"], wm.yaw_vocab_size)
        put("mst.pose_idx", pose_idx)
        put("mst.yaw_idx", yaw_idx)

        # MST evaluate with hooks on the blocks: tokens entering block 0, every block's output.
        blocks = wm.model.causal_time_space_blocks
        seen = {}
        hooks = [blocks[0].register_forward_pre_hook(lambda m, a: seen.__setitem__("mst.tokens_in", a[0]))]
        for i, blk in enumerate(blocks):
            hooks.append(blk.register_forward_hook(
                lambda m, a, o, i=i: seen.__setitem__(f"mst.block{i}_out", o)))
        try:
            stt, pose_emb = wm.model.evaluate(dev["mst.latents"], out["mst.pose_idx"].to(device),
                                              out["mst.yaw_idx"].to(device), sample_last=True)
        finally:
            for hk in hooks:
                hk.remove()
        for k, v in seen.items():
            put(k, v)
        put("mst.stt_features", stt)
        put("mst.pose_emb", pose_emb)

        img_ids, cond_ids, traj_ids = off.prepare_ids(B, h, w, s["T"], s["traj_len"], device)
        put("ids.img", img_ids)
        put("ids.cond", cond_ids)
        put("ids.traj", traj_ids)
        sched_traj = off.get_schedule(int(s["N"]), s["traj_len"])
        sched_img = off.get_schedule(int(s["N"]), s["L"])
        put("sched.traj", torch.tensor(sched_traj, dtype=torch.float32))
        put("sched.img", torch.tensor(sched_img, dtype=torch.float32))
        put("sched.real_traj_100", torch.tensor(off.get_schedule(100, 15), dtype=torch.float32))
        put("sched.real_img_100", torch.tensor(off.get_schedule(100, 512), dtype=torch.float32))

        # DiTs: stage inputs are the stored float32 values.
        cond = out["mst.stt_features"].to(device)
        y = out["mst.pose_emb"].to(device)
        ids_img, ids_cond, ids_traj = (out[k].to(device) for k in ("ids.img", "ids.cond", "ids.traj"))
        put("traj.velocity", wm.traj_dit(traj=dev["traj.x"], traj_ids=ids_traj, cond=cond, cond_ids=ids_cond,
                                         timesteps=dev["traj.t"]))
        put("vis.velocity", wm.dit(img=dev["vis.x"], img_ids=ids_img, cond=cond, cond_ids=ids_cond,
                                   timesteps=dev["vis.t"], y=y))
        traj = wm.traj_dit.sample(dev["traj.sample.noise"], ids_traj, cond, ids_cond, sched_traj)
        put("traj.sample.out", traj)
        put("traj.sample.out_denorm", wm.denormalize_traj(out["traj.sample.out"].clone().to(device)))
        put("vis.sample.out", wm.dit.sample(dev["vis.sample.noise"], ids_img, cond, ids_cond, y, sched_img))

        # Rollout: S calls of the official step_eval, its two torch.randn draws answered with the
        # stored noise, the window moved as scripts/test/test_free.py moves it.
        put_rollout(out, rollout(wm, dev, s, model_module))

    with dcae_ctx():
        out.update(dcae_outputs(ae, dev, s, rearrange))
    return out


def rollout(wm, dev, s, model_module):
    F, S = s["F"], s["S"]
    rec = {k: [] for k in ("stt_features", "pred_pose_idx", "pred_yaw_idx", "pose_emb", "predict_traj",
                           "predict_latents", "rel_pose_after", "rel_yaw_after")}
    latents, pose, yaw = dev["mst.latents"], dev["mst.rel_pose"], dev["mst.rel_yaw"]
    real_randn = torch.randn
    orig_eval, orig_pose_emb = wm.model.evaluate, wm.model.get_pose_emb

    def evaluate(*a, **k):
        r = orig_eval(*a, **k)
        rec["stt_features"].append(r[0].float().cpu())
        return r

    def get_pose_emb(p, y_):
        r = orig_pose_emb(p, y_)
        rec["pred_pose_idx"].append(p.float().cpu())
        rec["pred_yaw_idx"].append(y_.float().cpu())
        rec["pose_emb"].append(r.float().cpu())
        return r

    wm.model.evaluate, wm.model.get_pose_emb = evaluate, get_pose_emb
    try:
        for step in range(S):
            draws = [dev["rollout.noise_traj"][step], dev["rollout.noise_img"][step]]

            def randn(*shape, **kw):
                t = draws.pop(0)
                want = tuple(shape[0]) if len(shape) == 1 and isinstance(shape[0], (tuple, list)) else tuple(shape)
                if tuple(t.shape) != want:
                    raise RuntimeError(f"step_eval drew randn{want}, the stored noise is {tuple(t.shape)}")
                return t.clone()

            torch.randn = randn
            try:
                with quiet():
                    predict_traj, predict_latents = wm.step_eval(latents, pose, yaw, self_pred_traj=True)
            finally:
                torch.randn = real_randn
            if draws:
                raise RuntimeError("step_eval drew fewer noise tensors than expected")
            p, yv = predict_traj[:, 0:1, 0:2], predict_traj[:, 0:1, 2:3]
            pose = torch.cat((pose[:, 1:F], p, p), dim=1)
            yaw = torch.cat((yaw[:, 1:F], yv, yv), dim=1)
            rec["predict_traj"].append(predict_traj.float().cpu())
            rec["predict_latents"].append(predict_latents.float().cpu())
            rec["rel_pose_after"].append(pose.float().cpu())
            rec["rel_yaw_after"].append(yaw.float().cpu())
            nxt = predict_latents.reshape(predict_latents.shape[0], 1, -1, predict_latents.shape[-1])
            latents = torch.cat((latents[:, 1:F], nxt.to(latents.dtype)), dim=1)
    finally:
        wm.model.evaluate, wm.model.get_pose_emb = orig_eval, orig_pose_emb
    return rec


def put_rollout(out, rec):
    for k, v in rec.items():
        if len(v) != ROLLOUT_STEPS:
            raise RuntimeError(f"rollout.{k}: {len(v)} records for {ROLLOUT_STEPS} steps")
        out["rollout." + k] = torch.stack(v).contiguous()


def dcae_outputs(ae, dev, s, rearrange):
    out = {}
    seen = {}

    def grab(name):
        return lambda m, a, o: seen.__setitem__(name, o)

    orig_stb = ae.spatial_temporal_blocks

    def stb(xx):
        r = orig_stb(xx)
        seen.setdefault("temporal", r)
        return r

    def nchw(t, hh, ww):
        return rearrange(t, "b f (h w) c -> (b f) c h w", h=hh, w=ww)

    for i in DECODE_STAGES + ENCODE_STAGES:
        for side in (ae.decoder, ae.encoder):
            if len(side.stages[i].op_list) == 0:
                raise SystemExit(f"DC-AE stage {i} is empty in this configuration; the golden format needs it")
    ae.spatial_temporal_blocks = stb
    hooks = [ae.decoder.project_in.register_forward_hook(grab("dcae.decode.project_in_out"))]
    hooks += [ae.decoder.stages[i].register_forward_hook(grab(f"dcae.decode.stage{i}_out")) for i in DECODE_STAGES]
    try:
        lat = dev["dcae.decode.latent_in"]
        image = ae.decode(lat, is_video=False)
        out["dcae.decode.temporal_out"] = nchw(seen["temporal"], lat.shape[2], lat.shape[3])
        for k in ["dcae.decode.project_in_out"] + [f"dcae.decode.stage{i}_out" for i in DECODE_STAGES]:
            out[k] = seen[k]
        out["dcae.image"] = image
        for hk in hooks:
            hk.remove()
        hooks = [ae.encoder.stages[i].register_forward_hook(grab(f"dcae.encode.stage{i}_out")) for i in ENCODE_STAGES]
        seen.clear()
        img = image.float().contiguous()  # the decoder's output is the encoder's input (stored float32)
        out["dcae.encode.latent_out"] = ae.encode(img)
        for i in ENCODE_STAGES:
            out[f"dcae.encode.stage{i}_out"] = seen[f"dcae.encode.stage{i}_out"]
        for hk in hooks:
            hk.remove()
        hooks = []
        seen.clear()
        clip = dev["dcae.clip.latent_in"]
        ae.decode(clip, is_video=True)
        out["dcae.clip.temporal_out"] = nchw(seen["temporal"], clip.shape[2], clip.shape[3])
    finally:
        ae.spatial_temporal_blocks = orig_stb
        for hk in hooks:
            hk.remove()
    return {k: v.detach().float().cpu().contiguous() for k, v in out.items()}


# ---------------------------------------------------------------------------------------- measures

def measure(other, ref):
    o, r = other.double(), ref.double()
    finite = bool(torch.isfinite(other).all())
    max_abs = float((o - r).abs().max()) if o.numel() else 0.0
    ref_abs = float(r.abs().max()) if r.numel() else 0.0
    norm = float(r.norm())
    return {"max_abs": max_abs, "max_abs_ref": ref_abs,
            "rel_max": max_abs / ref_abs if ref_abs > 0 else (0.0 if max_abs == 0 else math.inf),
            "rel_l2": float((o - r).norm()) / norm if norm > 0 else (0.0 if max_abs == 0 else math.inf),
            "bitwise_equal": bool(other.shape == ref.shape and torch.equal(other, ref)), "finite": finite}


def measure_all(other, ref, names):
    return {k: measure(other[k], ref[k]) for k in names}


def autocast(device, dtype=torch.bfloat16):
    if device == "cpu":
        return lambda: cpu_autocast_like_cuda(dtype)
    return lambda: torch.autocast(device_type=device, dtype=dtype)


@contextlib.contextmanager
def cpu_autocast_like_cuda(dtype=torch.bfloat16):
    """CPU autocast made closer to CUDA's policy: matmuls/linears/convs in bf16 (CPU autocast already
    does that); layer_norm, group_norm and softmax in float32 (CUDA's float32 list; torch 1.13's CPU
    layer norm rejects bf16 input with float32 weights); batch_norm computed in float32 and returned
    in the input's dtype (as cuDNN's mixed-precision batch norm)."""
    import torch.nn.functional as Fn
    saved = {"layer_norm": Fn.layer_norm, "group_norm": Fn.group_norm, "softmax": Fn.softmax,
             "batch_norm": Fn.batch_norm, "torch_softmax": torch.softmax, "tensor_softmax": torch.Tensor.softmax}

    def f32(t):
        return t.float() if torch.is_tensor(t) and t.is_floating_point() else t

    def layer_norm(x, *a, **k):
        return saved["layer_norm"](f32(x), *a, **k)

    def group_norm(x, *a, **k):
        return saved["group_norm"](f32(x), *a, **k)

    def softmax(x, *a, **k):
        k.pop("dtype", None)
        return saved["softmax"](f32(x), *a, **k)

    def torch_softmax(x, *a, **k):
        k.pop("dtype", None)
        return saved["torch_softmax"](f32(x), *a, **k)

    def tensor_softmax(x, *a, **k):
        k.pop("dtype", None)
        return saved["tensor_softmax"](f32(x), *a, **k)

    def batch_norm(x, *a, **k):
        return saved["batch_norm"](f32(x), *a, **k).to(x.dtype)

    Fn.layer_norm, Fn.group_norm, Fn.softmax, Fn.batch_norm = layer_norm, group_norm, softmax, batch_norm
    torch.softmax, torch.Tensor.softmax = torch_softmax, tensor_softmax
    try:
        with torch.autocast(device_type="cpu", dtype=dtype):
            yield
    finally:
        Fn.layer_norm, Fn.group_norm, Fn.softmax, Fn.batch_norm = (saved["layer_norm"], saved["group_norm"],
                                                                   saved["softmax"], saved["batch_norm"])
        torch.softmax, torch.Tensor.softmax = saved["torch_softmax"], saved["tensor_softmax"]


@contextlib.contextmanager
def tf32_default():
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    # PyTorch's defaults: TF32 off for matmuls, on for cuDNN convolutions.
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = False, True
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def staged_bf16(off, wm, ae, x, s, device, ref):
    """The world model under bf16 autocast with float32 weights, each stage fed with the stored
    float32 values (the MST, the DiTs and the rollout run again; the DiTs take `ref`'s MST outputs)."""
    ctx = autocast(device)
    out = compute(off, wm, ae, x, s, device, world_ctx=ctx, dcae_ctx=tf32_default)
    # compute() feeds the DiTs its own (bf16) MST outputs; redo them from the stored float32 ones.
    with torch.no_grad(), ctx():
        dev = {k: v.to(device) for k, v in x.items()}
        cond, y = ref["mst.stt_features"].to(device), ref["mst.pose_emb"].to(device)
        ids_img, ids_cond, ids_traj = (ref[k].to(device) for k in ("ids.img", "ids.cond", "ids.traj"))
        sched_traj, sched_img = ref["sched.traj"].tolist(), ref["sched.img"].tolist()
        out["traj.velocity"] = wm.traj_dit(traj=dev["traj.x"], traj_ids=ids_traj, cond=cond, cond_ids=ids_cond,
                                           timesteps=dev["traj.t"]).float().cpu()
        out["vis.velocity"] = wm.dit(img=dev["vis.x"], img_ids=ids_img, cond=cond, cond_ids=ids_cond,
                                     timesteps=dev["vis.t"], y=y).float().cpu()
        t = wm.traj_dit.sample(dev["traj.sample.noise"], ids_traj, cond, ids_cond, sched_traj)
        out["traj.sample.out"] = t.float().cpu()
        out["traj.sample.out_denorm"] = wm.denormalize_traj(t.float().clone()).cpu()
        out["vis.sample.out"] = wm.dit.sample(dev["vis.sample.noise"], ids_img, cond, ids_cond, y, sched_img).float().cpu()
    # The encode case takes the stored image, not this run's.
    with tf32_default(), torch.no_grad():
        out.update(dcae_from_image(ae, ref["dcae.image"], device))
    return out


def dcae_from_image(ae, image, device):
    seen = {}
    hooks = [ae.encoder.stages[i].register_forward_hook(
        lambda m, a, o, i=i: seen.__setitem__(f"dcae.encode.stage{i}_out", o)) for i in ENCODE_STAGES]
    try:
        lat = ae.encode(image.to(device))
    finally:
        for hk in hooks:
            hk.remove()
    out = {"dcae.encode.latent_out": lat}
    out.update(seen)
    return {k: v.detach().float().cpu().contiguous() for k, v in out.items()}


def dcae_bf16(off, wm, ae, x, s, device, ref):
    with torch.no_grad():
        from einops import rearrange
        dev = {k: v.to(device) for k, v in x.items()}
        with autocast(device)():
            out = dcae_outputs(ae, dev, s, rearrange)
            out.update(dcae_from_image(ae, ref["dcae.image"], device))
    return out


# ---------------------------------------------------------------------------------------- main

def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--official", required=True, help="checkout of Kevin-thu/Epona")
    p.add_argument("--model", required=True, help="folder with configs.json and the two weight files")
    p.add_argument("--out", required=True)
    p.add_argument("--inputs-from", help="take every input tensor from this set's cases.safetensors")
    p.add_argument("--clip", help="clip folder (frames/*.png, poses.csv[, future_poses.csv, future/*.png])")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--set-name", help="the set's name (default: configs.json's 'set')")
    p.add_argument("--copy-weights", action="store_true")
    p.add_argument("--no-reload-check", action="store_true", help="skip the second build (halves the time)")
    p.add_argument("--no-bf16", action="store_true",
                   help="skip the bf16 measurements (the manifest then carries no bf16 limits: the bf16 tests fail)")
    a = p.parse_args()
    if a.inputs_from and a.clip:
        raise SystemExit("--inputs-from and --clip exclude each other")

    deterministic(a.device)
    off = official.load(a.official, a.device)
    modern_linspace_for_old_torch(a.official)
    configs = official.read_configs(os.path.join(a.model, "configs.json"))
    s = sizes(configs)
    set_name = a.set_name or weights_metadata(os.path.join(a.model, "weights_world.safetensors")).get("set") \
        or configs.get("set", "custom")
    log(f"model {a.model}: F={s['F']} latent {s['h']}x{s['w']} C={s['C']} N={s['N']}; DC-AE latent "
        f"{s['dh']}x{s['dw']} Tc={s['Tc']}; device {a.device}, torch {torch.__version__}")
    wm, ae = build_models(off, configs, a.model, a.device, init_seed=a.seed)

    provenance = {"inputs": "seeded generator", "seed": a.seed}
    if a.inputs_from:
        src = load_safetensors(os.path.join(a.inputs_from, "cases.safetensors"))
        x = {k: src[k].float().contiguous() for k in INPUTS}
        provenance = {"inputs": "cases.safetensors of " + os.path.abspath(a.inputs_from)}
    else:
        x = random_inputs(s, a.seed)
        if a.clip:
            x, info = clip_inputs(x, s, a.clip, ae, wm, a.device)
            provenance = {"inputs": "real clip (latents by this DC-AE) + seeded generator", "seed": a.seed, **info}
    expect = expected_shapes(s)
    for k in INPUTS:
        if list(x[k].shape) != expect[k]:
            raise SystemExit(f"input {k}: shape {list(x[k].shape)}, this model needs {expect[k]}")

    t0 = time.time()
    out = compute(off, wm, ae, x, s, a.device)
    log(f"float32 outputs: {time.time() - t0:.1f} s")
    for k, v in out.items():
        if list(v.shape) != expect[k]:
            raise SystemExit(f"output {k}: shape {list(v.shape)}, expected {expect[k]}")
        if not torch.isfinite(v).all():
            raise SystemExit(f"output {k} is not finite")
    names = [k for k in expect if k not in INPUTS]
    missing = set(names) - set(out)
    if missing:
        raise SystemExit(f"outputs not computed: {sorted(missing)}")

    tolerance, reload_check = {}, None
    if not a.no_reload_check:
        t0 = time.time()
        wm2, ae2 = build_models(off, configs, a.model, a.device, init_seed=a.seed + 1000)
        again = compute(off, wm2, ae2, x, s, a.device)
        tolerance["repeat_after_reload"] = measure_all(again, out, names)
        bad = [k for k in names if not torch.equal(again[k], out[k])]
        reload_check = {"all_outputs_bitwise_equal_after_official_reload": not bad, "not_equal": bad}
        log(f"reload check: {'bit-identical' if not bad else 'differs in ' + ', '.join(bad)} ({time.time() - t0:.1f} s)")
        del wm2, ae2
    if a.device == "cuda" and hasattr(torch.nn.functional, "scaled_dot_product_attention"):
        set_sdpa_math(False)
        tolerance["gpu_default_sdpa"] = measure_all(compute(off, wm, ae, x, s, a.device), out, names)
        set_sdpa_math(True)

    bf16 = None
    if not a.no_bf16:
        t0 = time.time()
        recipe = staged_bf16(off, wm, ae, x, s, a.device, out)
        dcae_names = [k for k in names if k.startswith("dcae.")]
        dref = dcae_bf16(off, wm, ae, x, s, a.device, out)
        bf16 = {
            "how": ("world model under torch.autocast(%s, bfloat16) with float32 weights, DCAE in float32 with "
                    "PyTorch's default TF32 flags; stage inputs from the stored float32 values" % a.device),
            "device": a.device if a.device == "cpu" else torch.cuda.get_device_name(0),
            "torch": torch.__version__,
            "note": ("CPU autocast (the official recipe is CUDA autocast): its op coverage differs, so these "
                     "figures are indicative" if a.device == "cpu" else "CUDA autocast, the official recipe"),
            "official_recipe_vs_fp32_golden": measure_all(recipe, out, names),
            "dcae_bf16_autocast_vs_fp32_golden": measure_all(dref, out, dcae_names),
        }
        log(f"bf16 recipe measured ({time.time() - t0:.1f} s)")

    write_set(a, configs, set_name, x, out, expect, tolerance, reload_check, bf16, provenance)


def expected_shapes(s):
    """name -> shape for this model, in the order of the public manifest (block outputs per MST layer)."""
    B, F, L, T, C, tl, S, v = s["B"], s["F"], s["L"], s["T"], s["C"], s["traj_len"], s["S"], s["vae"]
    N, h, w, dh, dw, Tc = s["N"], s["h"], s["w"], s["dh"], s["dw"], s["Tc"]
    H, W = s["image"]
    dw_, ew = s["widths"], s["enc_widths"]
    n_tok = 12
    e = {
        "emb.fourier.coords": [B, F + 1, 3], "temb.t": [4], "tok.rel_pose": [B, n_tok, 2], "tok.rel_yaw": [B, n_tok, 1],
        "mst.latents": [B, F, L, v], "mst.rel_pose": [B, F + 1, 2], "mst.rel_yaw": [B, F + 1, 1],
        "traj.x": [B, tl, 3], "traj.t": [B], "vis.x": [B, L, v], "vis.t": [B],
        "traj.sample.noise": [B, tl, 3], "vis.sample.noise": [B, L, v],
        "rollout.noise_traj": [S, B, tl, 3], "rollout.noise_img": [S, B, L, v],
        "dcae.decode.latent_in": [1, v, dh, dw], "dcae.clip.latent_in": [Tc, v, dh, dw],
        "emb.fourier.out": [B, F + 1, 3, 512], "temb.out": [4, 256],
        "tok.pose_idx": [B, n_tok, 2], "tok.yaw_idx": [B, n_tok, 1],
        "mst.pose_idx": [B, F + 1, 2], "mst.yaw_idx": [B, F + 1, 1], "mst.tokens_in": [B, F, T, C],
    }
    for i in range(s["n_mst"]):
        e[f"mst.block{i}_out"] = [B, F, T, C]
    e.update({
        "mst.stt_features": [B, T, C], "mst.pose_emb": [B, 3 * C],
        "ids.img": [B, L, 3], "ids.cond": [B, T, 3], "ids.traj": [B, tl, 3],
        "sched.traj": [N + 1], "sched.img": [N + 1], "sched.real_traj_100": [101], "sched.real_img_100": [101],
        "traj.velocity": [B, tl, 3], "vis.velocity": [B, L, v], "traj.sample.out": [B, tl, 3],
        "traj.sample.out_denorm": [B, tl, 3], "vis.sample.out": [B, L, v],
        "rollout.stt_features": [S, B, T, C], "rollout.pred_pose_idx": [S, B, 1, 2],
        "rollout.pred_yaw_idx": [S, B, 1, 1], "rollout.pose_emb": [S, B, 3 * C],
        "rollout.predict_traj": [S, B, tl, 3], "rollout.predict_latents": [S, B, h, w, v],
        "rollout.rel_pose_after": [S, B, F + 1, 2], "rollout.rel_yaw_after": [S, B, F + 1, 1],
        "dcae.decode.temporal_out": [1, v, dh, dw], "dcae.decode.project_in_out": [1, dw_[5], dh, dw],
        "dcae.decode.stage5_out": [1, dw_[5], dh, dw], "dcae.decode.stage4_out": [1, dw_[4], 2 * dh, 2 * dw],
        "dcae.image": [1, 3, H, W], "dcae.encode.latent_out": [1, v, dh, dw],
        "dcae.encode.stage3_out": [1, ew[4], 2 * dh, 2 * dw], "dcae.encode.stage4_out": [1, ew[5], dh, dw],
        "dcae.encode.stage5_out": [1, ew[5], dh, dw], "dcae.clip.temporal_out": [Tc, v, dh, dw],
    })
    return e


def weights_metadata(path):
    import struct
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        return json.loads(f.read(n)).get("__metadata__", {})


def copy_unless_same(src, dst):
    """tests/data/trained/configs.json links to the bundled model's: copying a file onto itself fails."""
    if not (os.path.exists(dst) and os.path.samefile(src, dst)):
        shutil.copyfile(src, dst)


def write_set(a, configs, set_name, x, out, expect, tolerance, reload_check, bf16, provenance):
    from safetensors.torch import save_file
    os.makedirs(a.out, exist_ok=True)
    template = json.load(open(os.path.join(TEMPLATE_DIR, "manifest.json")))["tensors"]
    tensors, cases = {}, {}
    for k, shape in expect.items():
        t = (x[k] if k in INPUTS else out[k]).float().contiguous()
        assert list(t.shape) == shape, (k, t.shape, shape)
        cases[k] = t
        if k in template:
            meaning = template[k]["meaning"]
        elif k.startswith("mst.block"):
            meaning = f"output of CausalTimeSpaceBlock {k[len('mst.block'):-len('_out')]}, (B, F, 3+L, C)"
        else:
            meaning = ""
        if a.clip and k in ("mst.latents", "mst.rel_pose", "mst.rel_yaw", "dcae.decode.latent_in",
                            "dcae.clip.latent_in", "vis.x", "traj.x"):
            meaning += " [from the clip: see provenance]"
        tensors[k] = {"role": "input" if k in INPUTS else "output", "shape": shape, "dtype": "float32",
                      "meaning": meaning}
    meta = {"producer": "epona training/make_fixtures.py (official Epona code)", "set": set_name,
            "seed": str(a.seed)}
    tmp = os.path.join(a.out, "cases.safetensors.tmp")
    save_file(cases, tmp, metadata=meta)
    os.replace(tmp, os.path.join(a.out, "cases.safetensors"))
    manifest = {
        "set": set_name,
        "producer": meta["producer"],
        "torch": torch.__version__,
        "device": a.device if a.device == "cpu" else torch.cuda.get_device_name(0),
        "dtype": "float32", "tf32": False, "sdpa_backend_for_reference": "math",
        "rollout_steps": ROLLOUT_STEPS,
        "model": os.path.abspath(a.model),
        "provenance": provenance,
        "reload_check": reload_check,
        "tensors": tensors,
        "weights_world": file_dtypes(os.path.join(a.model, "weights_world.safetensors")),
        "weights_dcae": file_dtypes(os.path.join(a.model, "weights_dcae.safetensors")),
        "tolerance": tolerance,
        "tolerance_official_bf16_recipe": bf16,
    }
    if reload_check is None:
        del manifest["reload_check"]
    if bf16 is None:
        del manifest["tolerance_official_bf16_recipe"]
    with open(os.path.join(a.out, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)
    copy_unless_same(os.path.join(a.model, "configs.json"), os.path.join(a.out, "configs.json"))
    if a.copy_weights:
        for n in ("weights_world.safetensors", "weights_dcae.safetensors"):
            shutil.copyfile(os.path.join(a.model, n), os.path.join(a.out, n))
    for n in ("weights_world.safetensors", "weights_dcae.safetensors"):
        got = weights_metadata(os.path.join(a.model, n)).get("set")
        if got != set_name:
            log(f"note: {n} carries metadata set={got!r}, the manifest says {set_name!r} "
                "(tests/io/safetensors.cpp compares them)")
    log(f"wrote {a.out}: {len(cases)} tensors ({sum(1 for k in cases if k in INPUTS)} inputs), set {set_name!r}")


if __name__ == "__main__":
    main()
