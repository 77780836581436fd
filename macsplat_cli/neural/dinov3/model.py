"""The DINOv3 ViT encoder modules: axial RoPE, the transformer blocks and :class:`DINOv3Encoder`.

Attribute names mirror the keys of the official checkpoints (see the package docstring).
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from macsplat_cli._checks import check_shape
from macsplat_cli.errors import ShapeError

from .config import DINOv3Config

__all__ = ["DINOv3Encoder", "DINOv3Output", "apply_rope", "rope_periods", "rope_sin_cos"]

logger = logging.getLogger(__name__)


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
    periods: torch.Tensor  # a buffer

    def __init__(self, head_dim: int, base: float) -> None:
        super().__init__()
        self.register_buffer("periods", rope_periods(head_dim, base), persistent=True)

    def forward(self, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        return rope_sin_cos(self.periods, h, w)


class _KMaskedLinear(nn.Linear):
    """The fused q/k/v projection; the key third of the bias is multiplied by ``bias_mask`` (zeros)."""

    bias_mask: torch.Tensor  # a buffer, present when the layer has a bias

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
