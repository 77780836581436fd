"""A MASt3R-compatible two-view network: CroCo ViT encoder, two cross-attending decoders, DPT + local-feature heads.

Written from the architecture description in ``shared/reference/mast3r_splatt3r.md`` §1 (no upstream code).
Module attribute names mirror the official state-dict keys (reference §1.7), so an official MASt3R
state dict loads with ``load_state_dict(strict=True)`` without renaming:

================================================  ==========================================================
key prefix                                        module
================================================  ==========================================================
``patch_embed.proj``                              Conv2d(3 → Ce, 16, stride 16)
``mask_token``                                    [1, 1, Cd] (CroCo pre-training leftover, unused)
``enc_blocks.{i}.{norm1,attn.qkv,attn.proj,``     pre-norm ViT blocks with 2-D RoPE
``norm2,mlp.fc1,mlp.fc2}``
``enc_norm``, ``decoder_embed``, ``dec_norm``     LayerNorm(Ce), Linear(Ce → Cd), LayerNorm(Cd)
``dec_blocks.{i}.*``, ``dec_blocks2.{i}.*``       decoder blocks of views 1 and 2: ``norm1, attn.{qkv,proj},
                                                  cross_attn.{projq,projk,projv,proj}, norm2, norm3, norm_y,
                                                  mlp.{fc1,fc2}``
``downstream_head{1,2}.dpt.*``                    DPT (point map + confidence), see :class:`.dpt.DPTAdapter`
``downstream_head{1,2}.head_local_features.*``    MLP ``fc1, fc2`` (descriptors + descriptor confidence)
================================================  ==========================================================

``…dpt.scratch.layer{1..4}_rn`` and ``…dpt.scratch.layer_rn.{0..3}`` are two names of the same four
convolutions (as upstream): ``state_dict()`` lists both.

Symbols: ``B`` batch, ``H``/``W`` image size (multiples of 16), ``h = H/16``, ``w = W/16``,
``N = h·w`` tokens, ``Ce``/``Cd`` encoder/decoder widths, ``D`` descriptor dimension.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from .._checks import check_shape
from ..errors import InputError, ShapeError
from .config import ActivationMode, BackboneConfig
from .dpt import DPTAdapter, tokens_to_map
from .rope import RoPE2D, patch_positions

__all__ = [
    "Attention",
    "BackboneView",
    "Block",
    "CrossAttention",
    "DecoderBlock",
    "MASt3RBackbone",
    "MASt3RHead",
    "Mlp",
    "PatchEmbed",
    "conf_activation",
    "depth_activation",
]

logger = logging.getLogger(__name__)

_LN_EPS = 1e-6


# ============================================================================================= outputs
@dataclass
class BackboneView:
    """MASt3R's outputs for one view of the pair.

    Attributes:
        pts3d: 3-D point of every pixel in **view 1's camera frame** (OpenCV axes, metres for the
            metric checkpoint); for view 2 this is upstream's ``pts3d_in_other_view``. [B, H, W, 3]
        conf: point-map confidence, ``≥ vmin`` of ``conf_mode`` (1 for MASt3R). [B, H, W]
        desc: L2-normalised local descriptors. [B, H, W, D]
        desc_conf: descriptor confidence, ``vmin + exp(x)`` (``vmin`` from ``desc_conf_mode``). [B, H, W]
        tokens: the decoder token list the heads read: entry 0 = encoder output after ``enc_norm``
            ``[B, N, Ce]``; entry ``k`` = output of decoder block ``k`` ``[B, N, Cd]``; the last entry has
            passed through ``dec_norm``. ``dec_depth + 1`` entries.
        grid: patch grid ``(h, w)``.
    """

    pts3d: torch.Tensor
    conf: torch.Tensor
    desc: torch.Tensor
    desc_conf: torch.Tensor
    tokens: tuple[torch.Tensor, ...]
    grid: tuple[int, int]

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W)"""
        return self.pts3d.shape[1], self.pts3d.shape[2]  # no int(): symbolic under torch.export

    @property
    def enc_tokens(self) -> torch.Tensor:
        """Encoder output tokens. [B, N, Ce]"""
        return self.tokens[0]

    @property
    def dec_tokens(self) -> torch.Tensor:
        """Last decoder layer's tokens (after ``dec_norm``), e.g. for a semantic-fusion module. [B, N, Cd]"""
        return self.tokens[-1]

    def dec_feature_map(self) -> torch.Tensor:
        """:attr:`dec_tokens` as a feature map on the patch grid. [B, Cd, h, w]"""
        return tokens_to_map(self.dec_tokens, self.grid)


# ============================================================================================= activations
def depth_activation(v: torch.Tensor, mode: ActivationMode) -> torch.Tensor:
    """Point-map activation on the last axis. ``exp``: ``v/|v| · (e^|v| − 1)``; ``linear``: ``v``. [..., 3]"""
    if mode[0] == "linear":
        return v
    assert mode[0] == "exp", mode
    d = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    return v / d.clamp_min(1e-8) * torch.expm1(d)


def conf_activation(x: torch.Tensor, mode: ActivationMode) -> torch.Tensor:
    """Confidence activation ``vmin + min(e^x, vmax − vmin)`` (``mode = ('exp', vmin, vmax)``). [...]"""
    assert mode[0] == "exp", mode
    vmin, vmax = mode[1], mode[2]
    return vmin + x.exp().clamp(max=vmax - vmin)


# ============================================================================================= transformer parts
class PatchEmbed(nn.Module):
    """Non-overlapping 16×16 patches → tokens (DUSt3R's ``PatchEmbedDust3R``: any H, W multiple of 16)."""

    def __init__(self, embed_dim: int, patch_size: int = 16) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)
        self.norm = nn.Identity()

    def forward(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
        """``img: [B, 3, H, W]`` → tokens ``[B, N, C]``, positions ``[N, 2]`` (y, x), grid ``(h, w)``."""
        x = self.proj(img)
        grid = (x.shape[2], x.shape[3])  # no int(): sizes stay symbolic under torch.export
        return self.norm(x.flatten(2).transpose(1, 2)), patch_positions(*grid, device=img.device), grid


class Mlp(nn.Module):
    """``fc2(GELU(fc1(x)))``."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_dim, hidden_dim)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_dim, out_dim if out_dim is not None else in_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """``[B, N, C]`` → ``[B, heads, N, C/heads]``."""
    b, n, c = x.shape
    return x.reshape(b, n, heads, c // heads).transpose(1, 2)


def _merge_heads(x: torch.Tensor) -> torch.Tensor:
    """``[B, heads, N, Dh]`` → ``[B, N, heads·Dh]``."""
    b, h, n, d = x.shape
    return x.transpose(1, 2).reshape(b, n, h * d)


class Attention(nn.Module):
    """Multi-head self-attention with 2-D RoPE on q and k, scaled by ``1/sqrt(Dh)``.

    ``qkv`` output layout ``[q | k | v]``, each head-major (``[heads, Dh]``): the usual ViT layout; the
    reference does not spell it out.
    """

    def __init__(self, dim: int, num_heads: int, rope: RoPE2D) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """``x: [B, N, C]``, ``pos: [N, 2]`` → ``[B, N, C]``."""
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]  # [B, heads, N, Dh]
        q, k = self.rope(q, pos), self.rope(k, pos)
        return self.proj(_merge_heads(F.scaled_dot_product_attention(q, k, v)))


class CrossAttention(nn.Module):
    """Multi-head cross-attention (queries from one view, keys/values from the other), 2-D RoPE on q and k."""

    def __init__(self, dim: int, num_heads: int, rope: RoPE2D) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.projq = nn.Linear(dim, dim)
        self.projk = nn.Linear(dim, dim)
        self.projv = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(
        self,
        query: torch.Tensor,  # [B, Nq, C]
        key: torch.Tensor,  # [B, Nk, C]
        value: torch.Tensor,  # [B, Nk, C]
        qpos: torch.Tensor,  # [Nq, 2]
        kpos: torch.Tensor,  # [Nk, 2]
    ) -> torch.Tensor:
        """Returns ``[B, Nq, C]``."""
        q = self.rope(_split_heads(self.projq(query), self.num_heads), qpos)
        k = self.rope(_split_heads(self.projk(key), self.num_heads), kpos)
        v = _split_heads(self.projv(value), self.num_heads)
        return self.proj(_merge_heads(F.scaled_dot_product_attention(q, k, v)))


class Block(nn.Module):
    """Pre-norm encoder block: ``x += Attn(LN x)``; ``x += MLP(LN x)``."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, rope: RoPE2D) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=_LN_EPS)
        self.attn = Attention(dim, num_heads, rope)
        self.norm2 = nn.LayerNorm(dim, eps=_LN_EPS)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), pos)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Decoder block: ``x += SelfAttn(LN1 x)``; ``x += CrossAttn(LN2 x, LN_y y)``; ``x += MLP(LN3 x)``."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, rope: RoPE2D, norm_mem: bool = True) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=_LN_EPS)
        self.attn = Attention(dim, num_heads, rope)
        self.cross_attn = CrossAttention(dim, num_heads, rope)
        self.norm2 = nn.LayerNorm(dim, eps=_LN_EPS)
        self.norm3 = nn.LayerNorm(dim, eps=_LN_EPS)
        self.norm_y: nn.Module = nn.LayerNorm(dim, eps=_LN_EPS) if norm_mem else nn.Identity()
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(
        self,
        x: torch.Tensor,  # [B, N, C] this view
        y: torch.Tensor,  # [B, M, C] the other view (previous layer)
        xpos: torch.Tensor,  # [N, 2]
        ypos: torch.Tensor,  # [M, 2]
    ) -> torch.Tensor:
        """Returns the updated tokens of this view. [B, N, C]"""
        x = x + self.attn(self.norm1(x), xpos)
        y_ = self.norm_y(y)
        x = x + self.cross_attn(self.norm2(x), y_, y_, xpos, ypos)
        return x + self.mlp(self.norm3(x))


# ============================================================================================= heads
class MASt3RHead(nn.Module):
    """One view's ``catmlp+dpt`` head: a DPT for point map + confidence, an MLP for descriptors + confidence.

    The MLP reads ``concat(encoder tokens, last decoder tokens)`` per patch and predicts ``(D + 1)·16²``
    values, reshaped channel-major to ``[(D+1)·256, h, w]`` and ``pixel_shuffle``-d by 16 to ``[D+1, H, W]``.
    """

    def __init__(self, config: BackboneConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.dpt = DPTAdapter(
            (c.enc_embed_dim, c.dec_embed_dim, c.dec_embed_dim, c.dec_embed_dim),
            c.dpt_hooks,
            out_channels=4,
            layer_dims=c.dpt_layer_dims,
            feature_dim=c.dpt_feature_dim,
            last_dim=c.dpt_last_dim,
        )
        self.head_local_features = Mlp(c.local_mlp_in_dim, c.local_mlp_hidden_dim, c.local_mlp_out_dim)

    def raw(self, tokens: Sequence[torch.Tensor], grid: tuple[int, int]) -> torch.Tensor:
        """Pre-activation map ``[pts3d 3 | conf 1 | desc D | desc_conf 1]``. [B, H, W, 5 + D]"""
        p = self.config.patch_size
        dense = self.dpt(tokens, grid)  # [B, 4, H, W]
        local = self.head_local_features(torch.cat((tokens[0], tokens[-1]), dim=-1))  # [B, N, (D+1)·p²]
        local = F.pixel_shuffle(tokens_to_map(local, grid), p)  # [B, D+1, H, W]
        return torch.cat((dense, local), dim=1).permute(0, 2, 3, 1)

    def forward(
        self, tokens: Sequence[torch.Tensor], grid: tuple[int, int]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Activated ``pts3d [B, H, W, 3]``, ``conf [B, H, W]``, ``desc [B, H, W, D]``, ``desc_conf [B, H, W]``."""
        c = self.config
        d = c.local_feat_dim
        raw = self.raw(tokens, grid)
        pts3d = depth_activation(raw[..., 0:3], c.depth_mode)
        conf = conf_activation(raw[..., 3], c.conf_mode)
        desc = F.normalize(raw[..., 4 : 4 + d], dim=-1)
        desc_conf = conf_activation(raw[..., 4 + d], c.desc_conf_mode)
        return pts3d, conf, desc, desc_conf


# ============================================================================================= the network
class MASt3RBackbone(nn.Module):
    """MASt3R (``AsymmetricMASt3R`` with ``catmlp+dpt`` heads) for one image pair.

    Example:
        >>> net = MASt3RBackbone(BackboneConfig.tiny()).eval()
        >>> v1, v2 = net(torch.zeros(1, 3, 48, 64), torch.zeros(1, 3, 48, 64))
        >>> tuple(v2.pts3d.shape), tuple(v2.desc.shape)
        ((1, 48, 64, 3), (1, 48, 64, 24))
    """

    def __init__(self, config: BackboneConfig | None = None) -> None:
        super().__init__()
        c = config if config is not None else BackboneConfig()
        self.config = c
        self.rope = RoPE2D(c.rope_freq)
        self.patch_embed = PatchEmbed(c.enc_embed_dim, c.patch_size)
        if c.mask_token:
            self.mask_token = nn.Parameter(torch.zeros(1, 1, c.dec_embed_dim))
        self.enc_blocks = nn.ModuleList(
            [Block(c.enc_embed_dim, c.enc_num_heads, c.mlp_ratio, self.rope) for _ in range(c.enc_depth)]
        )
        self.enc_norm = nn.LayerNorm(c.enc_embed_dim, eps=_LN_EPS)
        self.decoder_embed = nn.Linear(c.enc_embed_dim, c.dec_embed_dim)

        def decoder() -> nn.ModuleList:
            return nn.ModuleList(
                [
                    DecoderBlock(c.dec_embed_dim, c.dec_num_heads, c.mlp_ratio, self.rope, c.norm_im2_in_dec)
                    for _ in range(c.dec_depth)
                ]
            )

        self.dec_blocks = decoder()
        self.dec_blocks2 = decoder()
        self.dec_norm = nn.LayerNorm(c.dec_embed_dim, eps=_LN_EPS)
        self.downstream_head1 = MASt3RHead(c)
        self.downstream_head2 = MASt3RHead(c)

    # ------------------------------------------------------------------ stages
    def check_pair(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[int, int]:
        """Validate a pair of ``[B, 3, H, W]`` images (same shape, sides multiples of 16); returns (H, W).

        Raises:
            ShapeError: wrong rank or channel count, sides not multiples of 16, or different shapes.
            InputError: integer images.
        """
        p = self.config.patch_size
        check_shape(img1, ("B", 3, "H", "W"), "img1")
        h, w = img1.shape[2], img1.shape[3]
        if h % p or w % p or h == 0 or w == 0:
            raise ShapeError("img1", img1.shape, f"[B, 3, H, W] with H and W positive multiples of {p}")
        if img2.shape != img1.shape:
            raise ShapeError("img2", img2.shape, f"{list(img1.shape)} (both views must have the same size)")
        if not (img1.is_floating_point() and img2.is_floating_point()):
            raise InputError(f"images must be floating-point tensors in [-1, 1], got {img1.dtype} and {img2.dtype}")
        return h, w

    def encode(
        self, img1: torch.Tensor, img2: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[int, int]]:
        """Encode both views in one batch (shared weights).

        Returns ``enc1 [B, N, Ce]``, ``enc2 [B, N, Ce]`` (after ``enc_norm``), positions ``[N, 2]``, grid ``(h, w)``.
        """
        self.check_pair(img1, img2)
        b = img1.shape[0]
        x, pos, grid = self.patch_embed(torch.cat((img1, img2), dim=0))
        for blk in self.enc_blocks:
            x = blk(x, pos)
        x = self.enc_norm(x)
        return x[:b], x[b:], pos, grid

    def decode(
        self, enc1: torch.Tensor, enc2: torch.Tensor, pos: torch.Tensor
    ) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        """Run both decoders; at block ``k`` each view cross-attends to the other view's block ``k − 1`` output.

        Returns the two token lists described in :attr:`BackboneView.tokens` (``dec_depth + 1`` entries each).
        """
        out1: list[torch.Tensor] = [enc1]
        out2: list[torch.Tensor] = [enc2]
        f1, f2 = self.decoder_embed(enc1), self.decoder_embed(enc2)
        for blk1, blk2 in zip(self.dec_blocks, self.dec_blocks2):
            f1, f2 = blk1(f1, f2, pos, pos), blk2(f2, f1, pos, pos)
            out1.append(f1)
            out2.append(f2)
        out1[-1], out2[-1] = self.dec_norm(out1[-1]), self.dec_norm(out2[-1])
        return tuple(out1), tuple(out2)

    def predict_view(self, view: Literal[1, 2], tokens: Sequence[torch.Tensor], grid: tuple[int, int]) -> BackboneView:
        """Apply view ``view``'s head to a token list (e.g. one modified by a fusion module)."""
        head = self.downstream_head1 if view == 1 else self.downstream_head2
        pts3d, conf, desc, desc_conf = head(tokens, grid)
        return BackboneView(pts3d, conf, desc, desc_conf, tuple(tokens), grid)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[BackboneView, BackboneView]:
        """Predict both views' point maps (in view 1's frame), confidences and descriptors.

        Args:
            img1: view 1, RGB normalised to [-1, 1] (``(x − 0.5)/0.5``). [B, 3, H, W], H and W multiples of 16
            img2: view 2, same shape as ``img1``. [B, 3, H, W]

        Returns:
            ``(view1, view2)``: :class:`BackboneView` each, with ``pts3d [B, H, W, 3]``, ``conf [B, H, W]``,
            ``desc [B, H, W, D]``, ``desc_conf [B, H, W]`` and the decoder token lists.
        """
        enc1, enc2, pos, grid = self.encode(img1, img2)
        tok1, tok2 = self.decode(enc1, enc2, pos)
        return self.predict_view(1, tok1, grid), self.predict_view(2, tok2, grid)
