"""The DPT head (dense prediction transformer): four token maps of the decoder → one dense map at full resolution.

Written from the architecture description in ``shared/reference/mast3r_splatt3r.md`` §1 (no upstream code).
MASt3R's point-map head (:class:`~.backbone.MASt3RHead`) and Splatt3R's Gaussian head
(:class:`~.gaussian_head.GaussianHead`) each own one; attribute names mirror the official state-dict keys
(``act_postprocess``, ``scratch.layer{1..4}_rn`` aliased as ``scratch.layer_rn``, ``scratch.refinenet{1..4}``,
``head``).

Symbols: ``B`` batch, ``h``/``w`` the patch grid, ``N = h·w`` tokens, ``H = 16h``, ``W = 16w``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["DPTAdapter", "FeatureFusionBlock", "ResidualConvUnit", "tokens_to_map"]


def tokens_to_map(tokens: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Row-major tokens to a channels-first map: ``[B, h·w, C]`` → ``[B, C, h, w]``."""
    b, n, c = tokens.shape
    assert n == grid[0] * grid[1], (tokens.shape, grid)
    return tokens.transpose(1, 2).reshape(b, c, grid[0], grid[1])


class ResidualConvUnit(nn.Module):
    """``x + conv2(ReLU(conv1(ReLU(x))))`` with 3×3 convolutions (with bias)."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FeatureFusionBlock(nn.Module):
    """RefineNet fusion: ``out_conv(up2(RCU2(x + RCU1(skip))))`` (bilinear, ``align_corners=True``)."""

    def __init__(self, features: int) -> None:
        super().__init__()
        # resConfUnit1 exists (and is in the state dict) even where no skip input is given (refinenet4).
        self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, features, 1, bias=True)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class _Upsample2x(nn.Module):
    """Bilinear ×2 (``align_corners=True``); a parameter-free slot in the DPT head ``Sequential``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class _Scratch(nn.Module):
    """``layer{1..4}_rn`` (3×3 convs to the fusion width, no bias; aliased as ``layer_rn``) and ``refinenet{1..4}``."""

    def __init__(self, layer_dims: Sequence[int], features: int) -> None:
        super().__init__()
        self.layer1_rn = nn.Conv2d(layer_dims[0], features, 3, padding=1, bias=False)
        self.layer2_rn = nn.Conv2d(layer_dims[1], features, 3, padding=1, bias=False)
        self.layer3_rn = nn.Conv2d(layer_dims[2], features, 3, padding=1, bias=False)
        self.layer4_rn = nn.Conv2d(layer_dims[3], features, 3, padding=1, bias=False)
        self.layer_rn = nn.ModuleList([self.layer1_rn, self.layer2_rn, self.layer3_rn, self.layer4_rn])
        self.refinenet1 = FeatureFusionBlock(features)
        self.refinenet2 = FeatureFusionBlock(features)
        self.refinenet3 = FeatureFusionBlock(features)
        self.refinenet4 = FeatureFusionBlock(features)


class DPTAdapter(nn.Module):
    """Dense prediction transformer head over four token maps (keys ``act_postprocess``, ``scratch``, ``head``).

    Reassemble (``act_postprocess.{i}``): 1×1 conv to ``layer_dims[i]``, then transposed conv ×4 (i=0),
    ×2 (i=1), nothing (i=2), or a stride-2 3×3 conv (i=3): resolutions H/4, H/8, H/16, H/32. Then
    ``scratch.layer{i}_rn`` to ``feature_dim``, four RefineNet fusions from coarse to fine, and
    ``head`` = Conv3×3 → ×2 up → Conv3×3 → ReLU → Conv1×1 (``out_channels``), at full resolution.

    Args:
        token_dims: widths of the four hooked token lists, e.g. ``(1024, 768, 768, 768)``.
        hooks: indices of the four hooked entries in the decoder token list.
    """

    def __init__(
        self,
        token_dims: Sequence[int],
        hooks: Sequence[int],
        out_channels: int,
        layer_dims: Sequence[int] = (96, 192, 384, 768),
        feature_dim: int = 256,
        last_dim: int = 128,
    ) -> None:
        super().__init__()
        assert len(token_dims) == 4 and len(hooks) == 4 and len(layer_dims) == 4
        self.hooks = tuple(hooks)
        d0, d1, d2, d3 = layer_dims
        # The reference lists ``act_postprocess.{0..3}.{0,1}``; entry 2 has no resampling layer, so it has only
        # ``.0`` (this is what makes the DPT 20,201,668 parameters, the reference's count). Transposed convs
        # have a bias. The fusion order inside a RefineNet block (skip unit, second unit, ×2 up, 1×1 conv) and
        # the residual units (ReLU → conv → ReLU → conv, + input) follow the standard DPT design; the
        # reference names the parts but not their order.
        self.act_postprocess = nn.ModuleList(
            [
                nn.Sequential(nn.Conv2d(token_dims[0], d0, 1), nn.ConvTranspose2d(d0, d0, 4, stride=4)),
                nn.Sequential(nn.Conv2d(token_dims[1], d1, 1), nn.ConvTranspose2d(d1, d1, 2, stride=2)),
                nn.Sequential(nn.Conv2d(token_dims[2], d2, 1)),
                nn.Sequential(nn.Conv2d(token_dims[3], d3, 1), nn.Conv2d(d3, d3, 3, stride=2, padding=1)),
            ]
        )
        self.scratch = _Scratch(layer_dims, feature_dim)
        self.head = nn.Sequential(
            nn.Conv2d(feature_dim, feature_dim // 2, 3, padding=1),
            _Upsample2x(),
            nn.Conv2d(feature_dim // 2, last_dim, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(last_dim, out_channels, 1),
        )

    def forward(self, tokens: Sequence[torch.Tensor], grid: tuple[int, int]) -> torch.Tensor:
        """``tokens``: the decoder token list (``[B, N, ·]`` entries); ``grid = (h, w)`` → ``[B, out, 16h, 16w]``."""
        maps = [tokens_to_map(tokens[i], grid) for i in self.hooks]
        maps = [post(m) for post, m in zip(self.act_postprocess, maps)]
        l1, l2, l3, l4 = (rn(m) for rn, m in zip(self.scratch.layer_rn, maps))
        # H/32 is rounded up by the stride-2 conv: crop its ×2 up-sampling back to the H/16 map.
        p = self.scratch.refinenet4(l4)[:, :, : l3.shape[2], : l3.shape[3]]
        p = self.scratch.refinenet3(p, l3)
        p = self.scratch.refinenet2(p, l2)
        p = self.scratch.refinenet1(p, l1)
        return self.head(p)
