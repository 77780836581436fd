"""Splatt3R-style Gaussian head: one extra DPT per view predicting a 3-D Gaussian per pixel.

Written from ``shared/reference/mast3r_splatt3r.md`` §3.2 (no upstream code). The module tree
mirrors Splatt3R's checkpoint: ``downstream_head{1,2}.gaussian_dpt.dpt.*`` (the same DPT structure
as the point-map DPT, hooks ``(0, 6, 9, 12)``, with ``11 + 3K`` output channels). In a Splatt3R
Lightning checkpoint these keys carry an ``encoder.`` prefix, which
:func:`~macsplat_cli.neural.splatt3r.load_splatt3r` strips.

Per-pixel channel layout of the DPT output: ``[offset 3 | scale 3 | rotation 4 | sh 3·K | opacity 1]``.
Activations:

* offset ``Δ = v/|v| · (e^(|v|−6) − e^(−6))`` (tiny at init: |Δ| ≈ e^-6·|v| for small ``v``);
* scales ``s = e^raw`` (standard deviations, metres for the metric backbone);
* rotations ``q = raw/(|raw| + 1e-8)``, read as **(x, y, z, w)** (scalar last, as Splatt3R);
* SH: reshaped colour-major to ``[3, K]``, then the DC term gets ``RGB2SH(pixel colour)`` added
  (``(c − 0.5)/C0``), so the network predicts a residual on the input colour;
* opacity ``sigmoid(raw)``;
* means = point map (no gradient, as Splatt3R) + ``Δ``, in view 1's camera frame for both views.

The head returns these Gaussians as :class:`~macsplat_cli.gaussians.GaussianMaps`, macsplat's
(3DGS) parameterisation, built from the raw channels without an activation round trip:
``log_scales`` = the raw scale channels, ``opacity_logits`` = the raw opacity channel (exact at any
magnitude, where ``logit(sigmoid(raw))`` in float32 saturates), ``quats`` = the normalised rotation
reordered to (w, x, y, z), ``sh`` band-major ``[K, 3]``. So ``exp(log_scales)``,
``sigmoid(opacity_logits)``, ``quats`` and ``sh`` are exactly Splatt3R's activated values, reordered.

The final 1×1 convolution is initialised per channel group (Xavier-uniform gain, bias): offset
(0.001, 0.001), scale (3e-5, −7), rotation (1, 0), SH (1, 0), opacity (1, −2); other layers keep
PyTorch's default initialisation.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import nn

from .._checks import check_shape
from ..errors import ShapeError
from ..gaussians import GaussianMaps
from ..sh import rgb_to_sh0
from .backbone import BackboneView
from .config import BackboneConfig, GaussianHeadConfig
from .dpt import DPTAdapter

__all__ = ["GaussianDPT", "GaussianHead"]

_OFFSET_SHIFT = 6.0


class GaussianDPT(nn.Module):
    """Splatt3R's ``gaussian_dpt`` wrapper: its only child is ``dpt`` (a :class:`DPTAdapter`)."""

    def __init__(self, backbone: BackboneConfig, config: GaussianHeadConfig) -> None:
        super().__init__()
        c = backbone
        self.dpt = DPTAdapter(
            (c.enc_embed_dim, c.dec_embed_dim, c.dec_embed_dim, c.dec_embed_dim),
            c.dpt_hooks,
            out_channels=config.out_channels,
            layer_dims=c.dpt_layer_dims,
            feature_dim=c.dpt_feature_dim,
            last_dim=c.dpt_last_dim,
        )
        self._init_last_conv(config.sh_coeffs)

    @torch.no_grad()
    def _init_last_conv(self, k: int) -> None:
        conv = self.dpt.head[-1]
        assert isinstance(conv, nn.Conv2d) and conv.bias is not None
        groups = ((3, 0.001, 0.001), (3, 3e-5, -7.0), (4, 1.0, 0.0), (3 * k, 1.0, 0.0), (1, 1.0, -2.0))
        start = 0
        for n, gain, bias in groups:
            if conv.weight.device.type != "meta":
                nn.init.xavier_uniform_(conv.weight[start : start + n], gain=gain)
                conv.bias[start : start + n].fill_(bias)
            start += n
        assert start == conv.out_channels

    def forward(self, tokens: tuple[torch.Tensor, ...], grid: tuple[int, int]) -> torch.Tensor:
        """Pre-activation Gaussian parameters. [B, H, W, 11 + 3K]"""
        return self.dpt(tokens, grid).permute(0, 2, 3, 1)


class _ViewGaussianHead(nn.Module):
    """Holds one view's ``gaussian_dpt`` (so that keys read ``downstream_head{v}.gaussian_dpt.dpt.*``)."""

    def __init__(self, backbone: BackboneConfig, config: GaussianHeadConfig) -> None:
        super().__init__()
        self.gaussian_dpt = GaussianDPT(backbone, config)


class GaussianHead(nn.Module):
    """Per-pixel Gaussians for both views of a pair, from a :class:`MASt3RBackbone`'s outputs.

    Args:
        backbone: the backbone's configuration (token widths, DPT widths and hooks).
        config: SH size, offsets.
    """

    def __init__(self, backbone: BackboneConfig | None = None, config: GaussianHeadConfig | None = None) -> None:
        super().__init__()
        self.backbone_config = backbone if backbone is not None else BackboneConfig()
        self.config = config if config is not None else GaussianHeadConfig()
        self.downstream_head1 = _ViewGaussianHead(self.backbone_config, self.config)
        self.downstream_head2 = _ViewGaussianHead(self.backbone_config, self.config)

    def activate(self, raw: torch.Tensor, pts3d: torch.Tensor, rgb: torch.Tensor) -> tuple[GaussianMaps, torch.Tensor]:
        """Turn raw channels into Gaussians.

        Args:
            raw: pre-activation head output. [B, H, W, 11 + 3K]
            pts3d: the view's point map (in view 1's frame). [B, H, W, 3]
            rgb: the view's input colours in [0, 1], channels last. [B, H, W, 3]

        Returns:
            The Gaussians (in view 1's camera frame, ``valid`` and ``cam_to_world`` None), and the
            offsets ``Δ`` = means − point map (zero when offsets are off). [B, H, W, 3]
        """
        k = self.config.sh_coeffs
        offset_raw, scale_raw, rot_raw, sh_raw, opacity_raw = torch.split(raw, [3, 3, 4, 3 * k, 1], dim=-1)
        if self.config.use_offsets:
            d = torch.linalg.vector_norm(offset_raw, dim=-1, keepdim=True)
            offsets = offset_raw / d.clamp_min(1e-8) * (torch.exp(d - _OFFSET_SHIFT) - math.exp(-_OFFSET_SHIFT))
        else:
            offsets = torch.zeros_like(offset_raw)
        points = pts3d.detach() if self.config.detach_points else pts3d
        xyzw = rot_raw / (torch.linalg.vector_norm(rot_raw, dim=-1, keepdim=True) + 1e-8)  # Splatt3R's (x, y, z, w)
        sh = sh_raw.reshape(*sh_raw.shape[:-1], 3, k)  # colour-major, as Splatt3R
        sh = torch.cat((sh[..., :1] + rgb_to_sh0(rgb)[..., None], sh[..., 1:]), dim=-1)
        if self.config.max_scale is not None:  # log-scales: clamping them clamps the scales (no gradient above)
            scale_raw = scale_raw.clamp(max=math.log(self.config.max_scale))
        fields = (
            points + offsets,
            scale_raw,
            torch.cat((xyzw[..., 3:], xyzw[..., :3]), dim=-1),
            opacity_raw[..., 0],
            sh.transpose(-1, -2).contiguous(),
        )
        # Under autocast some fields come out in a lower precision than others: promote (losslessly) to one dtype.
        dtype = fields[0].dtype
        for t in fields[1:]:
            dtype = torch.promote_types(dtype, t.dtype)
        return GaussianMaps(*(t.to(dtype) for t in fields)), offsets

    def forward_view(self, view: Literal[1, 2], out: BackboneView, rgb: torch.Tensor) -> GaussianMaps:
        """Gaussians of view ``view`` (1 or 2). ``rgb``: input colours in [0, 1]. [B, 3, H, W]"""
        check_shape(rgb, (out.pts3d.shape[0], 3, *out.image_size), f"rgb{view}")
        if len(out.tokens) != self.backbone_config.dec_depth + 1:
            raise ShapeError(f"view {view} token list", (len(out.tokens),), f"[{self.backbone_config.dec_depth + 1}]")
        holder = self.downstream_head1 if view == 1 else self.downstream_head2
        raw = holder.gaussian_dpt(out.tokens, out.grid)
        return self.activate(raw, out.pts3d, rgb.permute(0, 2, 3, 1))[0]

    def forward(
        self, view1: BackboneView, view2: BackboneView, rgb1: torch.Tensor, rgb2: torch.Tensor
    ) -> tuple[GaussianMaps, GaussianMaps]:
        """Gaussians of both views (both in view 1's camera frame).

        Args:
            view1: backbone output of view 1.
            view2: backbone output of view 2.
            rgb1: view 1's colours in [0, 1] (``(img + 1)/2`` of the backbone input). [B, 3, H, W]
            rgb2: view 2's colours in [0, 1]. [B, 3, H, W]

        Returns:
            Two :class:`~macsplat_cli.gaussians.GaussianMaps` ``[B, H, W, ·]`` (``valid`` and
            ``cam_to_world`` None: every pixel, view 1's camera frame).
        """
        return self.forward_view(1, view1, rgb1), self.forward_view(2, view2, rgb2)
