"""The frozen DINOv3 ViT encoder that gives MAC-Splat its semantic features.

A clean-room implementation written from the description in the project's reference
notes (DINOv3 code is under the custom "DINOv3 License", so no upstream source is used).
Attribute names mirror the keys of the official checkpoints, so an official ``.pth``
loads with ``strict=True``; the Hugging Face layout is mapped onto the same names.

Architecture (all released ViTs): 16-px patch embedding (a strided conv), one CLS token
and 4 register ("storage") tokens, pre-norm blocks ``x + ls1(attn(norm1 x))``,
``x + ls2(ffn(norm2 x))`` with LayerScale, a GELU MLP (S, B, L) or a SwiGLU FFN
(S+, L+, H+: ``w3(silu(w1 x) * w2 x)``), a final LayerNorm (eps 1e-5). The key bias of
``attn.qkv`` is multiplied by the persistent buffer ``bias_mask`` (1 for q and v, 0 for k).

RoPE: axial 2-D rotary embedding on q and k of the *patch* tokens only (CLS and registers
untouched), computed inside ``forward`` from the patch grid of the input, so any
``H, W`` that are multiples of 16 work. Patch centres ``(i + 0.5)/h`` and ``(j + 0.5)/w``
are mapped to ``[-1, 1]``; ``angles = 2π·coord / periods`` for the y then the x
coordinate, tiled twice; rotation ``x·cos + rotate_half(x)·sin`` with the "halves"
convention. The periods are the persistent buffer ``rope_embed.periods`` [head_dim/4],
``base ** (2i / (head_dim/2))``, base 100. DINOv3's training-time RoPE augmentation
(shift, jitter, coordinate rescaling) is not implemented: the encoder is always in eval
mode, where it is off.

Shapes: ``B`` batch, ``H, W`` image size (multiples of 16), ``h = H/16``, ``w = W/16``,
``C`` embedding dim (384 S/S+, 768 B, 1024 L), ``R`` register tokens (4).

Weights are user-supplied (gated, see ``models/dinov3.md``); tests use random weights.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from macsplat_cli._checks import check_shape
from macsplat_cli.errors import InputError, ShapeError

from ._safetensors import read_safetensors as _read_safetensors

__all__ = [
    "DINOV3_PRESETS",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "SAT493M_MEAN",
    "SAT493M_STD",
    "DINOv3CheckpointError",
    "DINOv3Config",
    "DINOv3Encoder",
    "DINOv3Output",
    "DINOv3WeightsNotFoundError",
    "FfnType",
    "apply_rope",
    "hf_to_official",
    "infer_dinov3_config",
    "load_dinov3",
    "read_safetensors",
    "rope_periods",
    "rope_sin_cos",
]

logger = logging.getLogger(__name__)

FfnType = Literal["mlp", "swiglu"]

# Image normalisation of the LVD-1689M weights (ImageNet) and of the SAT-493M (satellite) weights.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SAT493M_MEAN = (0.430, 0.411, 0.296)
SAT493M_STD = (0.213, 0.156, 0.143)

WEIGHTS_HELP = (
    "DINOv3 weights are gated and never downloaded by macsplat: request them through the form on ai.meta.com "
    "(linked from github.com/facebookresearch/dinov3; the e-mailed URLs serve the official .pth files), or accept "
    "the licence of a facebook/dinov3-*-pretrain-* repository on Hugging Face and download its folder "
    "(config.json + model.safetensors). See models/dinov3.md."
)


class DINOv3CheckpointError(InputError):
    """A DINOv3 weight file is unreadable or does not match the model.

    Attributes:
        key: the first offending state-dict key (official naming), or None.
        file_shape: its shape in the file (None when the file lacks it).
        expected_shape: its shape in the model (None when the model has no such key).
    """

    def __init__(
        self,
        message: str,
        *,
        key: str | None = None,
        file_shape: tuple[int, ...] | None = None,
        expected_shape: tuple[int, ...] | None = None,
    ) -> None:
        self.key = key
        self.file_shape = file_shape
        self.expected_shape = expected_shape
        super().__init__(message)


class DINOv3WeightsNotFoundError(DINOv3CheckpointError, FileNotFoundError):
    """The DINOv3 weight file or folder does not exist; the message says where to get it."""


@dataclass(frozen=True)
class DINOv3Config:
    """Hyper-parameters of a DINOv3 ViT.

    Args:
        name: preset name (``vits16``, ``vits16plus``, ``vitb16``, ``vitl16``, ``tiny``) or a description.
        embed_dim: token width C.
        depth: number of transformer blocks.
        num_heads: attention heads; ``embed_dim / num_heads`` must be a multiple of 4 (axial RoPE).
        ffn: ``"mlp"`` (fc1 → GELU → fc2) or ``"swiglu"`` (``w3(silu(w1 x) * w2 x)``).
        ffn_hidden_dim: hidden width of the FFN (4·C for the MLPs; 1536 for S+, per its checkpoint).
        patch_size: patch size in pixels (16 for every release).
        n_storage_tokens: register tokens after the CLS token (4 for every release).
        qkv_bias: ``attn.qkv`` has a bias (and its ``bias_mask`` buffer); False only for ViT-7B.
        proj_bias: ``attn.proj`` has a bias.
        ffn_bias: the FFN linears have biases.
        layerscale_init: initial LayerScale gamma (random init only; checkpoints overwrite it).
        norm_eps: LayerNorm epsilon.
        rope_base: RoPE period base.
        untie_global_and_local_cls_norm: the checkpoint carries a ``local_cls_norm`` (ViT-L SAT-493M, ViT-7B);
            it is loaded but unused (training only).
        image_mean: per-channel mean of the normalisation the weights were trained with, on [0, 1] images.
        image_std: per-channel standard deviation, likewise.
    """

    name: str
    embed_dim: int
    depth: int
    num_heads: int
    ffn: FfnType
    ffn_hidden_dim: int
    patch_size: int = 16
    n_storage_tokens: int = 4
    qkv_bias: bool = True
    proj_bias: bool = True
    ffn_bias: bool = True
    layerscale_init: float = 1e-5
    norm_eps: float = 1e-5
    rope_base: float = 100.0
    untie_global_and_local_cls_norm: bool = False
    image_mean: tuple[float, float, float] = IMAGENET_MEAN
    image_std: tuple[float, float, float] = IMAGENET_STD

    def __post_init__(self) -> None:
        if self.embed_dim <= 0 or self.depth <= 0 or self.num_heads <= 0 or self.ffn_hidden_dim <= 0:
            raise ValueError(f"DINOv3Config {self.name!r}: sizes must be positive")
        if self.embed_dim % self.num_heads != 0 or (self.embed_dim // self.num_heads) % 4 != 0:
            raise ValueError(
                f"DINOv3Config {self.name!r}: head dim embed_dim/num_heads = {self.embed_dim}/{self.num_heads} "
                "must be a whole multiple of 4"
            )
        if self.ffn not in ("mlp", "swiglu"):
            raise ValueError(f"DINOv3Config {self.name!r}: ffn must be 'mlp' or 'swiglu', got {self.ffn!r}")

    @property
    def head_dim(self) -> int:
        """Per-head width ``embed_dim / num_heads`` (64 for S, S+, B, L)."""
        return self.embed_dim // self.num_heads

    @classmethod
    def preset(cls, name: str) -> DINOv3Config:
        """The named preset (see :data:`DINOV3_PRESETS`)."""
        try:
            return DINOV3_PRESETS[name]
        except KeyError:
            raise ValueError(f"unknown DINOv3 preset {name!r}; choose one of {', '.join(DINOV3_PRESETS)}") from None


DINOV3_PRESETS: dict[str, DINOv3Config] = {
    "vits16": DINOv3Config("vits16", embed_dim=384, depth=12, num_heads=6, ffn="mlp", ffn_hidden_dim=1536),
    "vits16plus": DINOv3Config("vits16plus", embed_dim=384, depth=12, num_heads=6, ffn="swiglu", ffn_hidden_dim=1536),
    "vitb16": DINOv3Config("vitb16", embed_dim=768, depth=12, num_heads=12, ffn="mlp", ffn_hidden_dim=3072),
    "vitl16": DINOv3Config("vitl16", embed_dim=1024, depth=24, num_heads=16, ffn="mlp", ffn_hidden_dim=4096),
    # Not a released model: a few-kB network with every kind of layer, for tests.
    "tiny": DINOv3Config("tiny", embed_dim=64, depth=2, num_heads=2, ffn="mlp", ffn_hidden_dim=128),
}

# Heads of the released widths, for the HF layout without a config.json (head dim 64, 128 for 7B).
_HEADS_BY_WIDTH = {384: 6, 768: 12, 1024: 16, 1280: 20, 4096: 32}


# --------------------------------------------------------------------------------------------------
# RoPE
# --------------------------------------------------------------------------------------------------


def rope_periods(head_dim: int, base: float = 100.0, *, device: torch.device | str | None = None) -> torch.Tensor:
    """RoPE periods ``base ** (2i / (head_dim/2))`` for ``i < head_dim/4``. [head_dim/4] float32"""
    n = head_dim // 4
    i = torch.arange(n, dtype=torch.float32, device=device)
    return base ** (2.0 * i / (head_dim // 2))


def rope_sin_cos(periods: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sine and cosine tables of the axial RoPE for an ``h × w`` patch grid (row-major tokens).

    Args:
        periods: RoPE periods. [P] with ``P = head_dim/4``
        h: patch rows.
        w: patch columns.

    Returns:
        ``(sin, cos)``, each [h·w, 4P] float32: per token the angles of the y coordinate
        (P frequencies), then of the x coordinate (P), the whole repeated twice.
    """
    p = periods.to(torch.float32)
    ys = (torch.arange(h, dtype=torch.float32, device=p.device) + 0.5) / h
    xs = (torch.arange(w, dtype=torch.float32, device=p.device) + 0.5) / w
    coords = torch.stack(torch.meshgrid(ys, xs, indexing="ij"), dim=-1).reshape(-1, 2)  # [hw, 2] (y, x)
    coords = 2.0 * coords - 1.0
    angles = (2.0 * math.pi) * coords[:, :, None] / p[None, None, :]  # [hw, 2, P]
    angles = angles.flatten(1).tile(2)  # [hw, 4P]
    return torch.sin(angles), torch.cos(angles)


def apply_rope(x: torch.Tensor, sin: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """Rotate ``x`` by the RoPE angles: ``x·cos + rotate_half(x)·sin``, ``rotate_half([a, b]) = [-b, a]``.

    Args:
        x: queries or keys of the patch tokens. [..., N, D]
        sin: [N, D]
        cos: [N, D]

    Returns:
        The rotated tensor, same shape and dtype as ``x`` (computed in at least float32).
    """
    ct = torch.promote_types(x.dtype, torch.float32)
    xf = x.to(ct)
    a, b = xf.chunk(2, dim=-1)
    rotated = torch.cat([-b, a], dim=-1)
    return (xf * cos.to(ct) + rotated * sin.to(ct)).to(x.dtype)


# --------------------------------------------------------------------------------------------------
# Layers (attribute names = official state-dict keys)
# --------------------------------------------------------------------------------------------------


class _PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=patch_size, stride=patch_size)


class _RopeEmbed(nn.Module):
    def __init__(self, head_dim: int, base: float) -> None:
        super().__init__()
        self.register_buffer("periods", rope_periods(head_dim, base), persistent=True)

    def forward(self, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        return rope_sin_cos(self.periods, h, w)


class _KMaskedLinear(nn.Linear):
    """The fused q/k/v projection; the key third of the bias is multiplied by ``bias_mask`` (zeros)."""

    def __init__(self, dim: int, bias: bool) -> None:
        super().__init__(dim, 3 * dim, bias=bias)
        if bias:
            mask = torch.ones(3 * dim)
            mask[dim : 2 * dim] = 0.0
            self.register_buffer("bias_mask", mask, persistent=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        bias = self.bias * self.bias_mask if self.bias is not None else None
        return F.linear(x, self.weight, bias)


class _Attention(nn.Module):
    def __init__(self, cfg: DINOv3Config) -> None:
        super().__init__()
        self.num_heads = cfg.num_heads
        self.qkv = _KMaskedLinear(cfg.embed_dim, bias=cfg.qkv_bias)
        self.proj = nn.Linear(cfg.embed_dim, cfg.embed_dim, bias=cfg.proj_bias)

    def forward(self, x: torch.Tensor, sin: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
        """x [B, N, C]; sin/cos [HW, head_dim] for the last HW tokens. Returns [B, N, C]."""
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # [B, heads, N, head_dim]
        prefix = n - sin.shape[0]
        q = torch.cat([q[:, :, :prefix], apply_rope(q[:, :, prefix:], sin, cos)], dim=2)
        k = torch.cat([k[:, :, :prefix], apply_rope(k[:, :, prefix:], sin, cos)], dim=2)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class _LayerScale(nn.Module):
    def __init__(self, dim: int, init: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int, bias: bool) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden, bias=bias)
        self.fc2 = nn.Linear(hidden, dim, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class _SwiGLU(nn.Module):
    def __init__(self, dim: int, hidden: int, bias: bool) -> None:
        super().__init__()
        self.w1 = nn.Linear(dim, hidden, bias=bias)
        self.w2 = nn.Linear(dim, hidden, bias=bias)
        self.w3 = nn.Linear(hidden, dim, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.w3(F.silu(self.w1(x)) * self.w2(x))


class _Block(nn.Module):
    def __init__(self, cfg: DINOv3Config) -> None:
        super().__init__()
        c = cfg.embed_dim
        self.norm1 = nn.LayerNorm(c, eps=cfg.norm_eps)
        self.attn = _Attention(cfg)
        self.ls1 = _LayerScale(c, cfg.layerscale_init)
        self.norm2 = nn.LayerNorm(c, eps=cfg.norm_eps)
        ffn_cls = _SwiGLU if cfg.ffn == "swiglu" else _Mlp
        self.mlp = ffn_cls(c, cfg.ffn_hidden_dim, cfg.ffn_bias)
        self.ls2 = _LayerScale(c, cfg.layerscale_init)

    def forward(self, x: torch.Tensor, sin: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), sin, cos))
        return x + self.ls2(self.mlp(self.norm2(x)))


# --------------------------------------------------------------------------------------------------
# Encoder
# --------------------------------------------------------------------------------------------------


class DINOv3Output(NamedTuple):
    """Outputs of :meth:`DINOv3Encoder.encode`, all after the final norm.

    Attributes:
        patch: patch features. [B, h, w, C]
        cls: the CLS token. [B, C]
        storage: the register tokens. [B, R, C]
    """

    patch: torch.Tensor
    cls: torch.Tensor
    storage: torch.Tensor


class DINOv3Encoder(nn.Module):
    """A frozen DINOv3 ViT: images in macsplat's [-1, 1] convention → patch features.

    Every parameter has ``requires_grad=False`` and the module is always in eval mode:
    ``train()`` is overridden so that neither ``encoder.train()`` nor a parent's
    ``model.train()`` switches it to training (DINOv3's RoPE would then randomly rescale
    its coordinates). Build it from a checkpoint with :func:`load_dinov3`; the
    constructor alone gives random weights (tests).

    State-dict keys are the official ones (188 for ViT-S/16, 212 for S+/16, 188 for
    B/16, 368 for L/16), ``rope_embed.periods`` and ``blocks.*.attn.qkv.bias_mask``
    included.
    """

    def __init__(self, config: DINOv3Config) -> None:
        super().__init__()
        self.config = config
        c = config.embed_dim
        self.cls_token = nn.Parameter(torch.zeros(1, 1, c))
        self.storage_tokens = nn.Parameter(torch.zeros(1, config.n_storage_tokens, c))
        self.mask_token = nn.Parameter(torch.zeros(1, c))  # training only; kept for strict loading
        self.patch_embed = _PatchEmbed(config.patch_size, c)
        self.rope_embed = _RopeEmbed(config.head_dim, config.rope_base)
        self.blocks = nn.ModuleList(_Block(config) for _ in range(config.depth))
        self.norm = nn.LayerNorm(c, eps=config.norm_eps)
        if config.untie_global_and_local_cls_norm:
            self.local_cls_norm = nn.LayerNorm(c, eps=config.norm_eps)  # training only
        self._init_random()
        self.requires_grad_(False)
        super().train(False)

    def _init_random(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        nn.init.normal_(self.cls_token, std=0.02)
        nn.init.normal_(self.storage_tokens, std=0.02)

    def train(self, mode: bool = True) -> DINOv3Encoder:
        """Stay in eval mode whatever ``mode`` says (the encoder is frozen)."""
        if mode:
            logger.debug("DINOv3Encoder.train(True) ignored: the encoder stays in eval mode")
        return super().train(False)

    def renormalize(self, img: torch.Tensor) -> torch.Tensor:
        """macsplat/MASt3R images in [-1, 1] → the encoder's normalisation: ``((x·0.5 + 0.5) − mean) / std``.

        Args:
            img: [B, 3, H, W] in [-1, 1]

        Returns:
            [B, 3, H, W] normalised with :attr:`DINOv3Config.image_mean` / ``image_std`` (ImageNet by default).
        """
        mean = torch.tensor(self.config.image_mean, dtype=img.dtype, device=img.device).view(1, 3, 1, 1)
        std = torch.tensor(self.config.image_std, dtype=img.dtype, device=img.device).view(1, 3, 1, 1)
        return (img * 0.5 + 0.5 - mean) / std

    def encode_normalized(self, x: torch.Tensor) -> DINOv3Output:
        """Run the ViT on images already normalised with the weights' mean/std (the official convention).

        Args:
            x: [B, 3, H, W] with H and W multiples of 16.

        Returns:
            :class:`DINOv3Output` with patch [B, H/16, W/16, C], cls [B, C], storage [B, R, C].

        Raises:
            ShapeError: ``x`` is not [B, 3, H, W] with H and W multiples of the patch size.
        """
        check_shape(x, ("B", 3, "H", "W"), "image")
        b, _, height, width = x.shape
        p = self.config.patch_size
        if height % p != 0 or width % p != 0:
            raise ShapeError("image", x.shape, f"[B, 3, H, W] with H and W multiples of {p}")
        h, w = height // p, width // p
        x = x.to(self.cls_token.dtype)
        patches = self.patch_embed.proj(x).flatten(2).transpose(1, 2)  # [B, hw, C]
        r = self.config.n_storage_tokens
        tokens = torch.cat([self.cls_token.expand(b, -1, -1), self.storage_tokens.expand(b, -1, -1), patches], dim=1)
        sin, cos = self.rope_embed(h, w)
        for block in self.blocks:
            tokens = block(tokens, sin, cos)
        tokens = self.norm(tokens)
        return DINOv3Output(
            patch=tokens[:, 1 + r :].reshape(b, h, w, -1), cls=tokens[:, 0], storage=tokens[:, 1 : 1 + r]
        )

    def encode(self, img: torch.Tensor) -> DINOv3Output:
        """Like :meth:`encode_normalized`, for images in [-1, 1]. img: [B, 3, H, W]"""
        check_shape(img, ("B", 3, "H", "W"), "image")
        return self.encode_normalized(self.renormalize(img))

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        """Patch features of images in [-1, 1].

        Args:
            img: [B, 3, H, W] in [-1, 1], H and W multiples of 16 (any aspect ratio).

        Returns:
            [B, H/16, W/16, C] features after the final norm.
        """
        return self.encode(img).patch


# --------------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------------


def read_safetensors(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Read a ``.safetensors`` file into CPU tensors (:func:`._safetensors.read_safetensors`).

    Raises:
        DINOv3CheckpointError: the file is truncated or its header is malformed.
    """
    return _read_safetensors(path, DINOv3CheckpointError)


_HF_BLOCK = re.compile(r"^(?:model\.)?layer\.(\d+)\.(.+)$")
_HF_TOP = {
    "embeddings.cls_token": "cls_token",
    "embeddings.mask_token": "mask_token",
    "embeddings.register_tokens": "storage_tokens",
    "embeddings.patch_embeddings.weight": "patch_embed.proj.weight",
    "embeddings.patch_embeddings.bias": "patch_embed.proj.bias",
    "norm.weight": "norm.weight",
    "norm.bias": "norm.bias",
}
_HF_BLOCK_SIMPLE = {
    "norm1.weight": "norm1.weight",
    "norm1.bias": "norm1.bias",
    "norm2.weight": "norm2.weight",
    "norm2.bias": "norm2.bias",
    "attention.o_proj.weight": "attn.proj.weight",
    "attention.o_proj.bias": "attn.proj.bias",
    "layer_scale1.lambda1": "ls1.gamma",
    "layer_scale2.lambda1": "ls2.gamma",
}
_HF_QKV = re.compile(r"^attention\.([qkv])_proj\.(weight|bias)$")
_HF_FFN = re.compile(r"^mlp\.(gate_proj|up_proj|down_proj)\.(weight|bias)$")


def hf_to_official(state_dict: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Map a Hugging Face ``DINOv3ViTModel`` state dict onto the official key names.

    ``q/k/v_proj`` are stacked into ``attn.qkv`` (a missing key bias becomes zeros and
    ``bias_mask`` is rebuilt: 1 for q and v, 0 for k — or 1 for k too when the file has a
    key bias), ``o_proj`` → ``attn.proj``, ``layer_scale{1,2}.lambda1`` → ``ls{1,2}.gamma``,
    ``mlp.up_proj/down_proj`` → ``mlp.fc1/fc2`` (SwiGLU: ``gate/up/down_proj`` →
    ``w1/w2/w3``), ``embeddings.*`` → ``cls_token``, ``storage_tokens``, ``mask_token``
    (reshaped to [1, C]), ``patch_embed.proj.*``. Keys may carry the in-memory
    ``model.`` prefix on ``layer.*`` or not (hub files). ``rope_embed.periods`` is *not*
    produced (HF has no such key; :func:`load_dinov3` recomputes it). ``*.inv_freq``
    (a derived RoPE buffer) is dropped.

    Raises:
        DINOv3CheckpointError: a key is unknown, or a block lacks one of q/k/v.
    """
    out: dict[str, torch.Tensor] = {}
    blocks: dict[int, dict[str, torch.Tensor]] = {}
    for key, t in state_dict.items():
        if key.endswith("inv_freq"):
            continue
        if key in _HF_TOP:
            out[_HF_TOP[key]] = t.reshape(1, -1) if key == "embeddings.mask_token" else t
            continue
        m = _HF_BLOCK.match(key)
        if m is None:
            raise DINOv3CheckpointError(
                f"unexpected key {key!r} with shape {list(t.shape)} in a Hugging Face DINOv3 state dict",
                key=key,
                file_shape=tuple(t.shape),
            )
        blocks.setdefault(int(m.group(1)), {})[m.group(2)] = t
    for i in sorted(blocks):
        parts = blocks[i]
        if "mlp.gate_proj.weight" in parts:  # SwiGLU
            ffn_names = {"gate_proj": "w1", "up_proj": "w2", "down_proj": "w3"}
        else:
            ffn_names = {"up_proj": "fc1", "down_proj": "fc2"}
        for rest, t in parts.items():
            if rest in _HF_BLOCK_SIMPLE:
                out[f"blocks.{i}.{_HF_BLOCK_SIMPLE[rest]}"] = t
            elif (fm := _HF_FFN.match(rest)) is not None and fm.group(1) in ffn_names:
                out[f"blocks.{i}.mlp.{ffn_names[fm.group(1)]}.{fm.group(2)}"] = t
            elif _HF_QKV.match(rest) is None:
                key = f"layer.{i}.{rest}"
                raise DINOv3CheckpointError(
                    f"unexpected key {key!r} with shape {list(t.shape)} in a Hugging Face DINOv3 state dict",
                    key=key,
                    file_shape=tuple(t.shape),
                )
        weights = []
        for x in "qkv":
            w = parts.get(f"attention.{x}_proj.weight")
            if w is None:
                key = f"layer.{i}.attention.{x}_proj.weight"
                raise DINOv3CheckpointError(f"missing key {key!r} in a Hugging Face DINOv3 state dict", key=key)
            weights.append(w)
        out[f"blocks.{i}.attn.qkv.weight"] = torch.cat(weights, dim=0)
        qb, kb, vb = (parts.get(f"attention.{x}_proj.bias") for x in "qkv")
        if qb is not None or kb is not None or vb is not None:
            c = weights[0].shape[0]
            zeros = weights[0].new_zeros(c)
            out[f"blocks.{i}.attn.qkv.bias"] = torch.cat([b if b is not None else zeros for b in (qb, kb, vb)])
            mask = torch.ones(3 * c, dtype=weights[0].dtype)
            if kb is None:
                mask[c : 2 * c] = 0.0
            out[f"blocks.{i}.attn.qkv.bias_mask"] = mask
    return out


def _need(state_dict: Mapping[str, torch.Tensor], key: str, what: str) -> torch.Tensor:
    t = state_dict.get(key)
    if t is None:
        raise DINOv3CheckpointError(f"cannot infer the DINOv3 variant: key {key!r} missing ({what})", key=key)
    return t


def infer_dinov3_config(state_dict: Mapping[str, torch.Tensor], *, num_heads: int | None = None) -> DINOv3Config:
    """Infer the variant from the shapes of an official-layout state dict (works on ``meta`` tensors).

    Width from ``cls_token``, patch size from ``patch_embed.proj.weight``, registers from
    ``storage_tokens``, depth from the ``blocks.{i}.norm1.weight`` keys, FFN type and width
    from ``blocks.0.mlp.{fc1,w1}.weight``, biases from the presence of their keys, the head
    dim from ``rope_embed.periods`` (4 × its length; else ``num_heads``, else the released
    models' head count for that width) and the RoPE base from the periods. A ViT-L with a
    ``local_cls_norm`` is the SAT-493M (satellite) model and gets its image normalisation.
    Named presets are recognised; anything else is named ``custom-…``.

    Raises:
        DINOv3CheckpointError: a key needed for the inference is missing (not a DINOv3 ViT).
    """
    if "cls_token" not in state_dict and any(k.startswith(("downsample_layers", "stages")) for k in state_dict):
        raise DINOv3CheckpointError("a DINOv3 ConvNeXt checkpoint: only the ViT variants are supported", key=None)
    c = int(_need(state_dict, "cls_token", "not a DINOv3 ViT checkpoint").shape[-1])
    patch = int(_need(state_dict, "patch_embed.proj.weight", "patch embedding").shape[-1])
    storage = state_dict.get("storage_tokens")
    n_storage = int(storage.shape[1]) if storage is not None and storage.dim() == 3 else 0
    depth = 0
    while f"blocks.{depth}.norm1.weight" in state_dict:
        depth += 1
    if depth == 0:
        _need(state_dict, "blocks.0.norm1.weight", "no transformer block")
    swiglu = "blocks.0.mlp.w1.weight" in state_dict
    first_ffn = "blocks.0.mlp.w1" if swiglu else "blocks.0.mlp.fc1"
    hidden = int(_need(state_dict, f"{first_ffn}.weight", "FFN").shape[0])
    periods = state_dict.get("rope_embed.periods")
    rope_base = 100.0
    if periods is not None and periods.dim() == 1 and periods.numel() > 0:
        head_dim = 4 * int(periods.numel())
        heads = c // head_dim if c % head_dim == 0 else 0
        if periods.numel() >= 2 and periods.device.type != "meta":
            rope_base = round(float(periods[1].double() ** periods.numel()), 4)
    elif num_heads:
        heads = num_heads
    else:
        heads = _HEADS_BY_WIDTH.get(c, c // 64)
        logger.warning("the DINOv3 weights do not give the head count: assuming %d heads for width %d", heads, c)
    if heads <= 0 or c % heads != 0 or (c // heads) % 4 != 0:
        raise DINOv3CheckpointError(f"cannot infer the DINOv3 head count for width {c}", key="rope_embed.periods")
    untie = "local_cls_norm.weight" in state_dict
    base = DINOv3Config(
        name="custom",
        embed_dim=c,
        depth=depth,
        num_heads=heads,
        ffn="swiglu" if swiglu else "mlp",
        ffn_hidden_dim=hidden,
        patch_size=patch,
        n_storage_tokens=n_storage,
        qkv_bias="blocks.0.attn.qkv.bias" in state_dict,
        proj_bias="blocks.0.attn.proj.bias" in state_dict,
        ffn_bias=f"{first_ffn}.bias" in state_dict,
        rope_base=rope_base,
        untie_global_and_local_cls_norm=untie,
    )
    for name, preset in DINOV3_PRESETS.items():
        if name == "tiny":
            continue
        if dataclasses.replace(base, name=name, untie_global_and_local_cls_norm=False) == preset:
            if not untie:
                return preset
            if name == "vitl16":
                logger.info("DINOv3 ViT-L with a local_cls_norm: the SAT-493M weights, using their normalisation")
                return dataclasses.replace(
                    preset,
                    name="vitl16-sat493m",
                    untie_global_and_local_cls_norm=True,
                    image_mean=SAT493M_MEAN,
                    image_std=SAT493M_STD,
                )
            return dataclasses.replace(base, name=f"{name}-untied")
    ffn = "swiglu" if swiglu else "mlp"
    return dataclasses.replace(base, name=f"custom-{c}d-{depth}x{heads}h-{ffn}{hidden}")


def _check_strict(
    expected: Mapping[str, torch.Tensor], got: Mapping[str, torch.Tensor], source: str, cfg: DINOv3Config
) -> None:
    """Raise on the first key that is missing, has another shape, or is unexpected (model order, then file order)."""
    for key, ref in expected.items():
        t = got.get(key)
        if t is None:
            raise DINOv3CheckpointError(
                f"{source}: key {key!r} (shape {list(ref.shape)} in DINOv3 {cfg.name}) is missing from the file",
                key=key,
                expected_shape=tuple(ref.shape),
            )
        if tuple(t.shape) != tuple(ref.shape):
            raise DINOv3CheckpointError(
                f"{source}: key {key!r} has shape {list(t.shape)} in the file but {list(ref.shape)} "
                f"in DINOv3 {cfg.name}",
                key=key,
                file_shape=tuple(t.shape),
                expected_shape=tuple(ref.shape),
            )
    for key, t in got.items():
        if key not in expected:
            raise DINOv3CheckpointError(
                f"{source}: unexpected key {key!r} with shape {list(t.shape)} (not in DINOv3 {cfg.name})",
                key=key,
                file_shape=tuple(t.shape),
            )


def _log_sha256(path: Path) -> None:
    if not logger.isEnabledFor(logging.DEBUG):
        return
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    logger.debug("DINOv3 weights %s sha256 %s", path, h.hexdigest())


def _not_found(what: Path, detail: str = "") -> DINOv3WeightsNotFoundError:
    return DINOv3WeightsNotFoundError(f"DINOv3 weights not found: {what}{detail}. {WEIGHTS_HELP}")


def _read_hf_folder(folder: Path) -> tuple[dict[str, torch.Tensor], dict]:
    single = folder / "model.safetensors"
    index = folder / "model.safetensors.index.json"
    files: list[Path]
    if single.is_file():
        files = [single]
    elif index.is_file():
        try:
            weight_map = json.loads(index.read_text(encoding="utf-8"))["weight_map"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise DINOv3CheckpointError(f"{index}: unreadable safetensors index: {e}") from None
        files = [folder / name for name in dict.fromkeys(weight_map.values())]
    else:
        raise _not_found(single, f" (the folder {folder} has no model.safetensors)")
    sd: dict[str, torch.Tensor] = {}
    for f in files:
        if not f.is_file():
            raise _not_found(f)
        _log_sha256(f)
        sd.update(read_safetensors(f))
    hf_config: dict = {}
    cfg_path = folder / "config.json"
    if cfg_path.is_file():
        try:
            hf_config = json.loads(cfg_path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DINOv3CheckpointError(f"{cfg_path}: unreadable config.json: {e}") from None
    else:
        logger.warning("%s has no config.json: assuming the released head count for the width", folder)
    return sd, hf_config


def _read_file(path: Path) -> dict[str, torch.Tensor]:
    _log_sha256(path)
    if path.suffix == ".safetensors":
        return read_safetensors(path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load's exception types are unspecified (IndexError on some garbage)
        raise DINOv3CheckpointError(f"{path}: not a readable PyTorch checkpoint: {type(e).__name__}: {e}") from e
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise DINOv3CheckpointError(
            f"{path}: expected a plain state dict (a mapping of names to tensors), got {type(obj).__name__}"
        )
    return dict(obj)


def load_dinov3(
    path: str | os.PathLike[str],
    config: DINOv3Config | None = None,
    *,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> DINOv3Encoder:
    """Load a frozen :class:`DINOv3Encoder` from user-supplied weights.

    Accepted layouts (told apart by their keys, not the file name):

    * the official ``.pth`` (a plain state dict, read with ``torch.load(weights_only=True)``);
    * a Hugging Face folder: ``config.json`` + ``model.safetensors`` (or a sharded
      ``model.safetensors.index.json``), keys mapped by :func:`hf_to_official`;
    * a single ``.safetensors`` file in either key layout.

    The sha256 of each weight file is logged at debug level (record it in ``models/dinov3.md``).

    Args:
        path: the ``.pth`` / ``.safetensors`` file or the HF folder.
        config: the expected variant; None infers it from the tensor shapes (:func:`infer_dinov3_config`).
        device: where the encoder lives.
        dtype: parameter dtype of the encoder (float32 by default; checkpoints are converted).

    Returns:
        The encoder in eval mode with ``requires_grad=False`` everywhere.

    Raises:
        DINOv3WeightsNotFoundError: the file or folder does not exist (the message says where to get weights).
        DINOv3CheckpointError: unreadable file, or a key missing / unexpected / of another shape than
            ``config`` (the message names the first such key and both shapes).
    """
    p = Path(path)
    if not p.exists():
        raise _not_found(p)
    hf_config: dict = {}
    if p.is_dir():
        sd, hf_config = _read_hf_folder(p)
    else:
        sd = _read_file(p)
    layout = "official"
    if any(k.startswith("embeddings.") for k in sd):
        layout = "huggingface"
        try:
            sd = hf_to_official(sd)
        except DINOv3CheckpointError as e:
            raise DINOv3CheckpointError(f"{p}: {e}", key=e.key, file_shape=e.file_shape) from None
    try:
        cfg = config or infer_dinov3_config(sd, num_heads=hf_config.get("num_attention_heads"))
    except DINOv3CheckpointError as e:
        raise DINOv3CheckpointError(f"{p}: {e}", key=e.key) from None
    if config is None and hf_config:
        width = hf_config.get("hidden_size", cfg.embed_dim)
        if width != cfg.embed_dim:
            raise DINOv3CheckpointError(
                f"{p}: config.json says hidden_size {width} but the weights have width {cfg.embed_dim}",
                key="embeddings.cls_token",
            )
        act = "silu" if cfg.ffn == "swiglu" else "gelu"
        if hf_config.get("hidden_act", act) != act:
            raise DINOv3CheckpointError(
                f"{p}: config.json hidden_act {hf_config['hidden_act']!r} is not supported "
                f"(DINOv3 uses {act!r} with a {cfg.ffn} FFN)"
            )
        cfg = dataclasses.replace(
            cfg,
            norm_eps=float(hf_config.get("layer_norm_eps", cfg.norm_eps)),
            rope_base=float(hf_config.get("rope_theta", cfg.rope_base)),
        )
    if layout == "huggingface" and "rope_embed.periods" not in sd:
        sd["rope_embed.periods"] = rope_periods(cfg.head_dim, cfg.rope_base)

    with torch.device("meta"):
        encoder = DINOv3Encoder(cfg)
    _check_strict(encoder.state_dict(), sd, str(p), cfg)
    encoder.to_empty(device="cpu")
    encoder.load_state_dict(sd, strict=True)
    encoder = encoder.to(device=device, dtype=dtype)
    encoder.rope_embed.periods = sd["rope_embed.periods"].to(device=device, dtype=torch.float32)  # keep fp32
    encoder.requires_grad_(False)
    encoder.eval()
    n_params = sum(t.numel() for t in encoder.parameters())
    logger.info("loaded DINOv3 %s (%s layout, %.1fM parameters) from %s", cfg.name, layout, n_params / 1e6, p)
    return encoder
