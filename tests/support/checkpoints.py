"""Tiny random-weight checkpoints in the official layouts, for the neural tests: MASt3R ``.pth`` state dicts built
from the key list and shapes the reference describes (``official_key_shapes``, independently of the module tree),
DINOv3 official state dicts (``official_spec``), and the set of tiny checkpoint files the CLI tests load
(:func:`write_tiny_checkpoints`)."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import torch

from macsplat_cli.neural import BackboneConfig, GaussianHead
from macsplat_cli.neural.dinov3 import DINOv3Config
from macsplat_cli.neural.fusion import FusionConfig, ResidualSemanticFusion, save_fusion

TINY = BackboneConfig.tiny()
TINY_ARGS = (
    "AsymmetricMASt3R(enc_depth=2, dec_depth=3, enc_embed_dim=64, enc_num_heads=2, dec_embed_dim=32, "
    "dec_num_heads=2, pos_embed='RoPE100', patch_embed_cls='PatchEmbedDust3R', img_size=(64, 64), "
    "head_type='catmlp+dpt', output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
    "two_confs=True, desc_conf_mode=('exp', 0, inf), landscape_only=False, dpt_layer_dims=(8, 16, 24, 32), "
    "dpt_feature_dim=16, dpt_last_dim=8, local_mlp_ratio=1.0)"
)
DINO_TINY = DINOv3Config.preset("tiny")  # 64-d features
SHALLOW = TINY.replace(enc_depth=1, dec_depth=2)
"""``TINY`` with one encoder block and two in each decoder (the fewest that keep the DPT heads' three decoder hooks
on decoder layers: ``(0, 1, 1, 2)``), for the ONNX export tests: torch.export's tracing time grows with the number
of blocks, and the graph carries every kind of block all the same."""
DINO_SHALLOW = dataclasses.replace(DINO_TINY, depth=1)
"""``DINO_TINY`` with one block, beside ``SHALLOW``."""


# ------------------------------------------------------------------------------ MASt3R: the reference key list
def dpt_shapes(p: str, c: BackboneConfig, out_channels: int) -> dict[str, tuple[int, ...]]:
    """``…dpt.*`` keys of reference §1.4/§1.7 (hooks' token widths: encoder, then three decoder layers)."""
    e, d = c.enc_embed_dim, c.dec_embed_dim
    l0, l1, l2, l3 = c.dpt_layer_dims
    f, last = c.dpt_feature_dim, c.dpt_last_dim
    s: dict[str, tuple[int, ...]] = {}

    def conv(name: str, cout: int, cin: int, k: int, bias: bool = True) -> None:
        s[f"{p}{name}.weight"] = (cout, cin, k, k)
        if bias:
            s[f"{p}{name}.bias"] = (cout,)

    conv("act_postprocess.0.0", l0, e, 1)
    s[f"{p}act_postprocess.0.1.weight"], s[f"{p}act_postprocess.0.1.bias"] = (l0, l0, 4, 4), (l0,)  # ConvTranspose ×4
    conv("act_postprocess.1.0", l1, d, 1)
    s[f"{p}act_postprocess.1.1.weight"], s[f"{p}act_postprocess.1.1.bias"] = (l1, l1, 2, 2), (l1,)  # ConvTranspose ×2
    conv("act_postprocess.2.0", l2, d, 1)
    conv("act_postprocess.3.0", l3, d, 1)
    conv("act_postprocess.3.1", l3, l3, 3)  # stride-2 conv
    for i, li in enumerate((l0, l1, l2, l3)):
        conv(f"scratch.layer{i + 1}_rn", f, li, 3, bias=False)
        conv(f"scratch.layer_rn.{i}", f, li, 3, bias=False)  # alias of the same tensor
    for r in range(1, 5):
        conv(f"scratch.refinenet{r}.out_conv", f, f, 1)
        for u in (1, 2):
            for v in (1, 2):
                conv(f"scratch.refinenet{r}.resConfUnit{u}.conv{v}", f, f, 3)
    conv("head.0", f // 2, f, 3)
    conv("head.2", last, f // 2, 3)
    conv("head.4", out_channels, last, 1)
    return s


def official_key_shapes(c: BackboneConfig) -> dict[str, tuple[int, ...]]:
    """Every state-dict key of AsymmetricMASt3R (catmlp+dpt) with its shape, as reference §1.2–§1.7 describes."""
    e, d = c.enc_embed_dim, c.dec_embed_dim
    s: dict[str, tuple[int, ...]] = {"patch_embed.proj.weight": (e, 3, 16, 16), "patch_embed.proj.bias": (e,)}
    s["mask_token"] = (1, 1, d)

    def linear(name: str, cout: int, cin: int) -> None:
        s[f"{name}.weight"], s[f"{name}.bias"] = (cout, cin), (cout,)

    def norm(name: str, dim: int) -> None:
        s[f"{name}.weight"], s[f"{name}.bias"] = (dim,), (dim,)

    for i in range(c.enc_depth):
        p = f"enc_blocks.{i}."
        norm(p + "norm1", e)
        linear(p + "attn.qkv", 3 * e, e)
        linear(p + "attn.proj", e, e)
        norm(p + "norm2", e)
        linear(p + "mlp.fc1", 4 * e, e)
        linear(p + "mlp.fc2", e, 4 * e)
    norm("enc_norm", e)
    linear("decoder_embed", d, e)
    for blocks in ("dec_blocks", "dec_blocks2"):
        for i in range(c.dec_depth):
            p = f"{blocks}.{i}."
            for n in ("norm1", "norm2", "norm3", "norm_y"):
                norm(p + n, d)
            linear(p + "attn.qkv", 3 * d, d)
            linear(p + "attn.proj", d, d)
            for n in ("projq", "projk", "projv", "proj"):
                linear(p + "cross_attn." + n, d, d)
            linear(p + "mlp.fc1", 4 * d, d)
            linear(p + "mlp.fc2", d, 4 * d)
    norm("dec_norm", d)
    hidden = int(c.local_mlp_ratio * (e + d))
    for h in (1, 2):
        s.update(dpt_shapes(f"downstream_head{h}.dpt.", c, 4))
        linear(f"downstream_head{h}.head_local_features.fc1", hidden, e + d)
        linear(f"downstream_head{h}.head_local_features.fc2", (c.local_feat_dim + 1) * 256, hidden)
    return s


def random_state_dict(c: BackboneConfig, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random tensors with the official names and shapes; aliased keys share one tensor, as in upstream files."""
    g = torch.Generator().manual_seed(seed)
    sd: dict[str, torch.Tensor] = {}
    for k, shape in official_key_shapes(c).items():
        if ".scratch.layer_rn." in k:
            i = int(k.rsplit(".", 2)[1])
            sd[k] = sd[k.replace(f"scratch.layer_rn.{i}", f"scratch.layer{i + 1}_rn")]
        elif k.endswith(".weight") and "norm" in k.rsplit(".", 2)[-2]:  # LayerNorm gains near 1
            sd[k] = 1 + 0.05 * torch.randn(shape, generator=g)
        else:
            fan_in = math.prod(shape[1:]) if len(shape) > 1 else 1
            sd[k] = torch.randn(shape, generator=g) / math.sqrt(max(fan_in, 1)) * (0.5 if len(shape) > 1 else 0.02)
    return sd


def save_pth(path: Path, sd: dict[str, torch.Tensor], args: str = TINY_ARGS) -> Path:
    """``sd`` saved as an official MASt3R ``.pth``: the weights under ``model``, the constructor string in ``args``."""
    torch.save({"model": sd, "args": argparse.Namespace(model=args, lr=1e-4, batch_size=8)}, path)
    return path


# ------------------------------------------------------------------------------ DINOv3: the official layout
def official_spec(
    c: int, depth: int, heads: int, hidden: int, ffn: str, *, n_reg: int = 4, patch: int = 16
) -> dict[str, tuple[int, ...]]:
    """Key → shape of an official DINOv3 ViT state dict (reference §1.3)."""
    spec: dict[str, tuple[int, ...]] = {
        "cls_token": (1, 1, c),
        "storage_tokens": (1, n_reg, c),
        "mask_token": (1, c),
        "patch_embed.proj.weight": (c, 3, patch, patch),
        "patch_embed.proj.bias": (c,),
        "rope_embed.periods": (c // heads // 4,),
    }
    for i in range(depth):
        b = f"blocks.{i}."
        spec |= {
            b + "norm1.weight": (c,),
            b + "norm1.bias": (c,),
            b + "attn.qkv.weight": (3 * c, c),
            b + "attn.qkv.bias": (3 * c,),
            b + "attn.qkv.bias_mask": (3 * c,),
            b + "attn.proj.weight": (c, c),
            b + "attn.proj.bias": (c,),
            b + "ls1.gamma": (c,),
            b + "norm2.weight": (c,),
            b + "norm2.bias": (c,),
            b + "ls2.gamma": (c,),
        }
        if ffn == "swiglu":
            spec |= {
                b + "mlp.w1.weight": (hidden, c),
                b + "mlp.w1.bias": (hidden,),
                b + "mlp.w2.weight": (hidden, c),
                b + "mlp.w2.bias": (hidden,),
                b + "mlp.w3.weight": (c, hidden),
                b + "mlp.w3.bias": (c,),
            }
        else:
            spec |= {
                b + "mlp.fc1.weight": (hidden, c),
                b + "mlp.fc1.bias": (hidden,),
                b + "mlp.fc2.weight": (c, hidden),
                b + "mlp.fc2.bias": (c,),
            }
    spec |= {"norm.weight": (c,), "norm.bias": (c,)}
    return spec


def random_official_state_dict(cfg: DINOv3Config, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random weights in the official layout, scaled so that attention, RoPE and every block matter."""
    g = torch.Generator().manual_seed(seed)
    c, hd = cfg.embed_dim, cfg.embed_dim // cfg.num_heads
    sd: dict[str, torch.Tensor] = {}
    for key, shape in official_spec(c, cfg.depth, cfg.num_heads, cfg.ffn_hidden_dim, cfg.ffn).items():
        if key.endswith("bias_mask"):
            t = torch.cat([torch.ones(c), torch.zeros(c), torch.ones(c)])
        elif key == "rope_embed.periods":
            t = torch.tensor([100.0 ** (2 * i / (hd / 2)) for i in range(hd // 4)])
        elif key.endswith("gamma"):
            t = 0.5 + 0.1 * torch.randn(shape, generator=g)
        elif key.endswith(("norm1.weight", "norm2.weight", "norm.weight")):
            t = 1.0 + 0.1 * torch.randn(shape, generator=g)
        elif len(shape) >= 2 and key.endswith("weight"):
            fan_in = math.prod(shape[1:])
            gain = 3.0 if "qkv" in key else 1.0  # peaky attention, so that positions matter
            t = gain * torch.randn(shape, generator=g) / math.sqrt(fan_in)
        else:
            t = 0.1 * torch.randn(shape, generator=g)
        sd[key] = t.float()
    return sd


# ------------------------------------------------------------------------------ checkpoint files
def write_tiny_checkpoints(
    root: Path, backbone: BackboneConfig = TINY, dino: DINOv3Config = DINO_TINY
) -> dict[str, Path]:
    """Tiny random-weight checkpoints in the official layouts, in ``root``: MASt3R ``.pth`` (``mast3r``),
    DINOv3 (``dino``), fusion (``fusion``), Splatt3R ``.ckpt`` (``splatt3r``), and a mismatched MASt3R (``bad``).
    ``backbone`` and ``dino`` other than ``TINY`` and ``DINO_TINY`` (e.g. ``SHALLOW``, ``DINO_SHALLOW``) change the
    networks' depths; the layouts stay the official ones."""
    args = TINY_ARGS if backbone == TINY else backbone.to_args_string()
    files = {"mast3r": save_pth(root / "mast3r_tiny.pth", random_state_dict(backbone), args=args)}
    torch.save(random_official_state_dict(dino, seed=1), root / "dinov3_tiny.pth")
    files["dino"] = root / "dinov3_tiny.pth"
    torch.manual_seed(0)
    fusion = ResidualSemanticFusion(FusionConfig(desc_dim=24, dino_dim=dino.embed_dim, hidden_dim=16))
    with torch.no_grad():  # as after training: a non-zero last layer, so the fusion changes the descriptors
        fusion.layers[-1].weight.normal_(0.0, 0.5)
    files["fusion"] = save_fusion(fusion, root / "fusion.pth")
    # Splatt3R: a Lightning checkpoint holding the frozen MASt3R and the Gaussian head under "encoder."
    cfg = backbone.replace(head_type="gaussian_head", desc_conf_mode=("exp", 1.0, math.inf))
    torch.manual_seed(1)
    head = GaussianHead(cfg).state_dict()
    state = {"encoder." + k: v for k, v in {**random_state_dict(cfg), **head}.items()}
    state["lpips_criterion.scaling_layer.shift"] = torch.zeros(1, 3, 1, 1)
    torch.save({"state_dict": state, "epoch": 19, "global_step": 1200}, root / "splatt3r_tiny.ckpt")
    files["splatt3r"] = root / "splatt3r_tiny.ckpt"
    bad = random_state_dict(backbone)
    bad["dec_blocks.1.mlp.fc1.weight"] = torch.zeros(16, 32)
    files["bad"] = save_pth(root / "mismatched.pth", bad, args=args)
    return files
