"""The official Epona modules, imported from a checkout of Kevin-thu/Epona given by path.

epona contains none of the official code: this module puts the checkout on sys.path and builds
the official `TrainTransformersDiT` (MST + VisDiT + TrajDiT) and `DCAE` from a configuration in
the golden `configs.json` layout (tests/data/golden/configs.json), so that training, export and
the parity fixtures all use one description of the model. Where a package the official code
imports is missing (omegaconf everywhere; einops, safetensors and triton on Debian), a minimal stand-in
from this repository is used (benchmarks/pytorch/omegaconf.py, training/stand_ins/).

On the CPU the official `.cuda()` calls become no-ops and its Triton RMSNorm2d kernel is replaced
by its formula (as benchmarks/pytorch/official_bench.py does).
"""
import copy
import importlib.util
import json
import os
import sys
import types

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _add_stand_ins():
    sys.path.insert(0, os.path.join(ROOT, "benchmarks", "pytorch"))  # omegaconf stand-in
    for name in ("einops", "safetensors", "triton"):
        if importlib.util.find_spec(name) is None:
            sys.path.append(os.path.join(HERE, "stand_ins"))
            break


def _sdpa(q, k, v, attn_mask=None, dropout_p=0.0, is_causal=False, scale=None):
    """scaled_dot_product_attention for torch < 2.0 (Debian's python3-torch), math backend."""
    s = (q @ k.transpose(-2, -1)) * (scale if scale is not None else q.shape[-1] ** -0.5)
    if is_causal:
        L, S = q.shape[-2], k.shape[-2]
        s = s.masked_fill(torch.ones(L, S, dtype=torch.bool, device=q.device).tril().logical_not(), float("-inf"))
    if attn_mask is not None:
        s = s.masked_fill(attn_mask.logical_not(), float("-inf")) if attn_mask.dtype == torch.bool else s + attn_mask
    return torch.softmax(s, dim=-1) @ v


def load(checkout, device, triton_rmsnorm=True):
    """Imports the official modules; returns a namespace of what the harness uses.

    triton_rmsnorm=False replaces the DC-AE's Triton RMSNorm2d by its formula on every device
    (training: plain autograd, no dependence on the machine's Triton version)."""
    if not os.path.isfile(os.path.join(checkout, "models", "model.py")):
        raise SystemExit(f"--official {checkout}: not a checkout of Kevin-thu/Epona (no models/model.py)")
    _add_stand_ins()
    if not hasattr(torch.nn.functional, "scaled_dot_product_attention"):
        torch.nn.functional.scaled_dot_product_attention = _sdpa
    sys.path.insert(0, os.path.abspath(checkout))
    if device == "cpu":
        torch.nn.Module.cuda = lambda self, *a, **k: self
        torch.Tensor.cuda = lambda self, *a, **k: self
    from models.model import TrainTransformersDiT  # noqa: E402
    from models.modules import dcae as dcae_module  # noqa: E402
    from models.modules import sampling  # noqa: E402
    from models.modules.tokenizer import poses_to_indices, yaws_to_indices  # noqa: E402
    from utils import preprocess  # noqa: E402
    if device == "cpu" or not triton_rmsnorm:
        _patch_triton_rmsnorm()
    if device == "cpu":
        sampling.prepare_ids.__defaults__ = ("cpu",)
        # DCAE.spatial_temporal_blocks moves its mask with .cuda(): already a no-op above.
    return types.SimpleNamespace(TrainTransformersDiT=TrainTransformersDiT, dcae=dcae_module,
                                 get_schedule=sampling.get_schedule, prepare_ids=sampling.prepare_ids,
                                 poses_to_indices=poses_to_indices, yaws_to_indices=yaws_to_indices,
                                 get_rel_pose=preprocess.get_rel_poses_from_abs,
                                 get_rel_traj=preprocess.get_rel_traj_from_abs)


def _patch_triton_rmsnorm():
    from models.modules.dcae_layers import norm

    def forward(self, x):  # RMSNorm2d: per pixel over channels, then weight and bias
        r = torch.rsqrt(x.float().pow(2).mean(dim=1, keepdim=True) + self.eps)
        return ((x * r) * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)).to(x.dtype)

    norm.TritonRMSNorm2d.forward = forward


def read_configs(path):
    with open(path) as f:
        return json.load(f)


def world_args(configs):
    """The official `args` namespace (config file + command-line defaults) from configs.json."""
    wmc = dict(configs["world_model_config"])
    wmc.setdefault("batch_size", 1)
    wmc["image_size"] = tuple(wmc["image_size"])
    return types.SimpleNamespace(**wmc)


def build_world(off, configs, device, batch_size=1):
    args = world_args(configs)
    args.batch_size = batch_size
    wm = off.TrainTransformersDiT(args, local_rank=0, condition_frames=args.condition_frames)
    return wm.to(device)


def build_dcae(off, configs, device):
    """The official DCAE with the widths, depths and clip length of configs.json's `dcae` section."""
    d = configs["dcae"]["config"]
    cfg = off.dcae.dc_ae_f32c32("dc-ae-f32c32-mix-1.0", add_encoder_temporal=False,
                                add_decoder_temporal=d["add_decoder_temporal"],
                                condition_frames=d["condition_frames"], token_size=d["token_size"])
    for side in ("encoder", "decoder"):
        for key in ("width_list", "depth_list", "block_type"):
            setattr(getattr(cfg, side), key, list(d[side][key]))
    cfg.decoder.norm = list(d["decoder"]["norm"])
    cfg.decoder.act = list(d["decoder"]["act"])
    return off.dcae.DCAE(cfg).to(device)


def make_configs(template_path, world_overrides, dcae_widths, dcae_depths, temporal_frames, set_name):
    """A configs.json (golden layout) for a model of the given sizes, derived sections recomputed."""
    c = copy.deepcopy(read_configs(template_path))
    w = c["world_model_config"]
    w.update(world_overrides)
    H, W = w["image_size"]
    h, wl = H // w["downsample_size"], W // w["downsample_size"]
    L = h * wl
    c["set"] = set_name
    c["derived"].update(latent_h=h, latent_w=wl, img_tokens=L, total_tokens=L + 3,
                        mst_head_dim=w["n_embd"] // w["n_head"],
                        mst_block_size_attr=w["condition_frames"] * (L + 3))
    c["mst"].update(n_embd=w["n_embd"], n_head=w["n_head"], n_layer_causal_time_space=w["n_layer"][0])
    c["vis_dit"].update(vec_in_dim=3 * w["n_embd"], context_in_dim=w["n_embd"], hidden_size=w["n_embd_dit"],
                        num_heads=w["n_head_dit"], depth=w["n_layer"][1], depth_single_blocks=w["n_layer"][2],
                        axes_dim=w["axes_dim_dit"])
    c["traj_dit"].update(context_in_dim=w["n_embd"], hidden_size=w["n_embd_dit_traj"],
                         num_heads=w["n_head_dit_traj"], depth=w["n_layer_traj"][0],
                         depth_single_blocks=w["n_layer_traj"][1], axes_dim=w["axes_dim_dit_traj"])
    d = c["dcae"]
    cfg = d["config"]
    for side in ("encoder", "decoder"):
        cfg[side]["width_list"] = list(dcae_widths)
        cfg[side]["depth_list"] = list(dcae_depths[side])
    cfg["condition_frames"] = temporal_frames
    cfg["token_size"] = L
    d["image_size"] = [H, W]
    d["latent_size"] = [h, wl]
    d["token_size"] = L
    d["temporal_frames"] = temporal_frames
    d["config_string"] = (
        "latent_channels=32 encoder.block_type=[ResBlock,ResBlock,ResBlock,EViT_GLU,EViT_GLU,EViT_GLU] "
        f"encoder.width_list=[{','.join(map(str, dcae_widths))}] "
        f"encoder.depth_list=[{','.join(map(str, dcae_depths['encoder']))}] "
        "decoder.block_type=[ResBlock,ResBlock,ResBlock,EViT_GLU,EViT_GLU,EViT_GLU] "
        f"decoder.width_list=[{','.join(map(str, dcae_widths))}] "
        f"decoder.depth_list=[{','.join(map(str, dcae_depths['decoder']))}] "
        "decoder.norm=[bn2d,bn2d,bn2d,trms2d,trms2d,trms2d] decoder.act=[relu,relu,relu,silu,silu,silu]")
    d["litemla"]["dim"] = 32
    w["temporal_patch_size"] = temporal_frames
    c.pop("golden", None)
    return c
