"""DINOv3 ViT variants: :class:`DINOv3Config`, the released presets and the image normalisations."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from ..constructor import ModelConfigError

__all__ = [
    "DINOV3_PRESETS",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "SAT493M_MEAN",
    "SAT493M_STD",
    "DINOv3Config",
    "FfnType",
]

FfnType = Literal["mlp", "swiglu"]

# (field, least, most) of the sizes a config may have.
_BOUNDS = (
    ("embed_dim", 1, 8192),
    ("depth", 1, 64),
    ("num_heads", 1, 256),
    ("ffn_hidden_dim", 1, 32768),
    ("patch_size", 8, 64),
    ("n_storage_tokens", 0, 64),
)

# Image normalisation of the LVD-1689M weights (ImageNet) and of the SAT-493M (satellite) weights.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SAT493M_MEAN = (0.430, 0.411, 0.296)
SAT493M_STD = (0.213, 0.156, 0.143)


@dataclass(frozen=True)
class DINOv3Config:
    """Hyper-parameters of a DINOv3 ViT.

    Sizes are bounded (depth ≤ 64, width ≤ 8192, ≤ 256 heads, FFN ≤ 32768, patch 8–64, ≤ 64 registers):
    invalid or out-of-range values raise :class:`~macsplat_cli.neural.constructor.ModelConfigError`
    (an ``InputError`` and a ``ValueError``).

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
        sizes = [getattr(self, key) for key, _, _ in _BOUNDS]
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in sizes):
            raise ModelConfigError(f"DINOv3Config {self.name!r}: sizes must be whole numbers")
        if self.embed_dim <= 0 or self.depth <= 0 or self.num_heads <= 0 or self.ffn_hidden_dim <= 0:
            raise ModelConfigError(f"DINOv3Config {self.name!r}: sizes must be positive")
        # Bounds: configurations come from untrusted files (shapes, config.json); ViT-7B is well inside.
        for key, lo, hi in _BOUNDS:
            value = getattr(self, key)
            if not lo <= value <= hi:
                raise ModelConfigError(
                    f"DINOv3Config {self.name!r}: {key}={value} is out of range (a whole number from {lo} to {hi})"
                )
        if self.embed_dim % self.num_heads != 0 or (self.embed_dim // self.num_heads) % 4 != 0:
            raise ModelConfigError(
                f"DINOv3Config {self.name!r}: head dim embed_dim/num_heads = {self.embed_dim}/{self.num_heads} "
                "must be a whole multiple of 4"
            )
        if self.ffn not in ("mlp", "swiglu"):
            raise ModelConfigError(f"DINOv3Config {self.name!r}: ffn must be 'mlp' or 'swiglu', got {self.ffn!r}")
        for key in ("rope_base", "norm_eps"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ModelConfigError(f"DINOv3Config {self.name!r}: {key}={value!r} must be a positive finite number")

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
